//! The HTTP listeners (`/metrics` and the page) of a real `guardiand` against hostile
//! clients on loopback: oversized requests, hundreds of idle connections, a foreign `Host`.
//! The daemon's memory and threads (from `/proc`) stay bounded, and a normal request is
//! answered again once the hostile clients are gone. The figures are printed
//! (`cargo test -p guardian-tests --test http -- --nocapture`) and kept in
//! `docs/reliability.md`.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

use guardian_tests::harness::{self, Daemon, Setup};

/// A `/proc/<pid>/status` field (kB for memory).
fn status(pid: u32, field: &str) -> u64 {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(field))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{field} in\n{text}"))
}

/// Send `head` (without the final blank line) and read the status code answered.
fn ask(address: &str, head: &str) -> u16 {
    let mut s = TcpStream::connect(address).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let _ = write!(s, "{head}\r\n\r\n");
    let mut text = String::new();
    let _ = s.read_to_string(&mut text);
    text.split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0)
}

fn setup() -> Setup {
    let mut s = Setup::new(95);
    s.tables.push_str("[web]\naddress = \"127.0.0.1:0\"\n");
    s
}

#[test]
fn oversized_requests_and_foreign_hosts_are_refused_and_memory_stays_put() {
    let s = setup();
    let d = Daemon::start(&s);
    let (metrics, page) = (d.metrics_address(), d.page_address());
    assert_eq!(
        ask(
            &metrics,
            &format!("GET /metrics HTTP/1.1\r\nHost: {metrics}")
        ),
        200
    );
    let rss_before = status(d.pid(), "VmRSS:");
    // 64 requests whose line is 4 MiB long, to both ports: each is cut at 8 KiB.
    let line = "a".repeat(4 << 20);
    for address in [&metrics, &page] {
        for _ in 0..32 {
            let mut s = TcpStream::connect(address.as_str()).unwrap();
            s.set_write_timeout(Some(Duration::from_secs(10))).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
            // The daemon answers and closes long before the line ends: writing fails.
            let _ = write!(s, "GET /{line} HTTP/1.1\r\nHost: {address}\r\n\r\n");
            let mut text = String::new();
            let _ = s.read_to_string(&mut text);
            assert!(
                text.is_empty() || text.starts_with("HTTP/1.1 431"),
                "{text:.80}"
            );
        }
    }
    let rss_after = status(d.pid(), "VmRSS:");
    println!("VmRSS before {rss_before} kB, after 64 requests of 4 MiB {rss_after} kB");
    assert!(
        rss_after < rss_before + 10 * 1024,
        "memory grew from {rss_before} kB to {rss_after} kB"
    );
    // DNS rebinding: a foreign Host is refused on both ports, the address is served.
    for address in [&metrics, &page] {
        assert_eq!(
            ask(address, "GET / HTTP/1.1\r\nHost: evil.example.com"),
            421
        );
        assert_eq!(ask(address, "GET / HTTP/1.1"), 421, "no Host");
    }
    assert_eq!(ask(&page, &format!("GET / HTTP/1.1\r\nHost: {page}")), 200);
    let port = page.rsplit(':').next().unwrap();
    assert_eq!(
        ask(&page, &format!("GET / HTTP/1.1\r\nHost: localhost:{port}")),
        200
    );
}

#[test]
fn idle_connections_take_no_threads_and_the_listener_recovers() {
    let s = setup();
    let d = Daemon::start(&s);
    let metrics = d.metrics_address();
    assert_eq!(
        ask(
            &metrics,
            &format!("GET /metrics HTTP/1.1\r\nHost: {metrics}")
        ),
        200
    );
    let threads_before = status(d.pid(), "Threads:");
    // 300 connections that never send a byte.
    let idle: Vec<TcpStream> = (0..300)
        .map(|_| TcpStream::connect(metrics.as_str()).unwrap())
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    let threads_during = status(d.pid(), "Threads:");
    println!("threads before {threads_before}, with 300 idle connections {threads_during}");
    assert_eq!(threads_during, threads_before);
    // Meanwhile a scraper gets an answer (busy or the metrics), never a hang.
    let code = ask(
        &metrics,
        &format!("GET /metrics HTTP/1.1\r\nHost: {metrics}"),
    );
    assert!(code == 200 || code == 503, "{code}");
    drop(idle);
    // Once they are gone (cut off after 2 s at most), scrapes are answered again.
    let start = std::time::Instant::now();
    loop {
        let code = ask(
            &metrics,
            &format!("GET /metrics HTTP/1.1\r\nHost: {metrics}"),
        );
        if code == 200 {
            break;
        }
        assert!(start.elapsed() < harness::PATIENCE, "{code}");
        std::thread::sleep(Duration::from_millis(100));
    }
}
