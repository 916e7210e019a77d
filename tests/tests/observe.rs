//! What the screen stops (issue 43), against a real `guardiand`: its verdict record listed
//! by `guardianctl verdicts`, its `/metrics` checked by Debian's `promtool` and scraped by a
//! real Prometheus server, and its page loaded in headless Chromium, which must show the
//! stopped plan beside its claimed class. The tools are Debian packages `.ci/run` installs
//! (`prometheus`, `chromium`); a missing one fails the test.

use std::io::Write;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use guardian_client::Client;
use guardian_tests::harness::{self, Daemon, PATIENCE, Setup, http_get, http_get_accept, traj};

/// Enroll task0..task3 and check one genuine plan (go) and the same plan claimed as
/// another task (wrong task), as in e2e.rs with this model.
fn setup_with_a_stop(tables: &str) -> (Setup, Daemon, Client) {
    let mut s = Setup::new(7);
    s.extra = "default-threshold = 1e9\nk-nearest = 3".into();
    s.tables = tables.to_owned();
    let d = Daemon::start(&s);
    let client = s.client();
    harness::enroll_tasks(&client, &[0, 1, 2, 3]);
    let genuine = traj(1, 11);
    assert!(client.check(&genuine, "task1").expect("check").is_go());
    let stop = client.check(&genuine, "task2").expect("check");
    assert!(!stop.is_go(), "{stop:?}");
    (s, d, client)
}

/// A tool from a Debian package: its path, or a failing test naming the package.
fn tool(name: &str, package: &str) -> String {
    let found = Command::new("sh")
        .args(["-c", &format!("command -v {name}")])
        .output()
        .is_ok_and(|o| o.status.success());
    assert!(
        found,
        "{name} is missing: install the Debian package `{package}` (.ci/run does)"
    );
    name.to_owned()
}

/// A child process killed on drop.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Run `cmd` to its end, killed after `limit`; its stdout.
fn run_bounded(mut cmd: Command, limit: Duration) -> (std::process::ExitStatus, String, String) {
    let out_dir = tempfile::tempdir().expect("tempdir");
    let (o, e) = (out_dir.path().join("stdout"), out_dir.path().join("stderr"));
    let mut child = Killed(
        cmd.stdout(std::fs::File::create(&o).expect("stdout file"))
            .stderr(std::fs::File::create(&e).expect("stderr file"))
            .stdin(Stdio::null())
            .spawn()
            .expect("spawn"),
    );
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.0.try_wait().expect("wait") {
            break s;
        }
        assert!(start.elapsed() < limit, "{cmd:?} ran longer than {limit:?}");
        std::thread::sleep(Duration::from_millis(50));
    };
    let read = |p: &Path| std::fs::read_to_string(p).unwrap_or_default();
    (status, read(&o), read(&e))
}

/// The no-go rows of `guardianctl verdicts --no-go --json`, waiting for the writer.
fn no_go_rows(s: &Setup) -> Vec<serde_json::Value> {
    let record = s.state_dir().join("verdicts.sqlite");
    let start = Instant::now();
    loop {
        let out = Command::new(harness::ctl_bin())
            .args(["--json", "verdicts", "--no-go", "--record"])
            .arg(&record)
            .output()
            .expect("run guardianctl");
        if out.status.success() {
            let rows: Vec<serde_json::Value> =
                serde_json::from_slice(&out.stdout).expect("JSON rows");
            if !rows.is_empty() {
                return rows;
            }
        }
        assert!(
            start.elapsed() < PATIENCE,
            "no no-go verdict recorded: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn verdicts_are_listed_and_metrics_pass_promtool() {
    let promtool = tool("promtool", "prometheus");
    let (s, d, _client) = setup_with_a_stop(harness::METRICS_ANY_PORT);

    // The record: the wrong-task stop, its figures and plan; filters work.
    let rows = no_go_rows(&s);
    assert_eq!(rows.len(), 1, "{rows:?}");
    let r = &rows[0];
    assert_eq!(r["claimed"], "task2");
    assert_eq!(r["reason"], "wrong-task");
    assert_eq!(r["nearest"][0]["class"], "task1");
    assert_eq!(r["plan_kept"], true);
    // Wrong task: the nearest class is nearer than the claimed one.
    let nearest = r["nearest"][0]["distance"]
        .as_f64()
        .expect("nearest distance");
    assert!(r["distance"].as_f64().expect("distance") > nearest, "{r}");
    assert!(
        r["margin"].as_f64().is_some() && r["gap"].as_f64().unwrap() < 0.0,
        "{r}"
    );
    assert_eq!(r["service"], s.service.as_str());
    let record = s.state_dir().join("verdicts.sqlite");
    let list = |args: &[&str]| {
        let out = Command::new(harness::ctl_bin())
            .args(["--json", "verdicts", "--record"])
            .arg(&record)
            .args(args)
            .output()
            .expect("run guardianctl");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice::<Vec<serde_json::Value>>(&out.stdout).expect("JSON")
    };
    assert_eq!(list(&[]).len(), 2);
    assert_eq!(list(&["--class", "task1"]).len(), 1);
    assert_eq!(list(&["--since", "1h"]).len(), 2);
    assert_eq!(list(&["--since", "2099-01-01T00:00:00Z"]).len(), 0);
    let table = Command::new(harness::ctl_bin())
        .args(["verdicts", "--no-go", "--record"])
        .arg(&record)
        .output()
        .expect("run guardianctl");
    let table = String::from_utf8_lossy(&table.stdout);
    assert!(
        table.contains("wrong-task") && table.contains("task2"),
        "{table}"
    );

    // /metrics: the checks by verdict, reason and class; promtool accepts the exposition.
    let address = d.metrics_address();
    let (code, text) = http_get(&address, "/metrics").expect("scrape");
    assert_eq!(code, 200);
    for needle in [
        "guardian_checks_total{verdict=\"go\",reason=\"none\",class=\"task1\"} 1",
        "guardian_checks_total{verdict=\"no-go\",reason=\"wrong-task\",class=\"task2\"} 1",
        "guardian_check_duration_seconds_count 2",
        "guardian_bank_classes 4",
        "guardian_bank_version 4",
        "guardian_model_info{version=",
        "guardian_record_enabled 1",
    ] {
        assert!(text.contains(needle), "{needle} missing:\n{text}");
    }
    let mut child = Command::new(&promtool)
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run promtool");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(text.as_bytes())
        .unwrap();
    let out = child.wait_with_output().expect("promtool");
    assert!(
        out.status.success(),
        "promtool check metrics failed:\n{}{}\n{text}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // A scraper asking for OpenMetrics gets it (Prometheus does; its scrape is tested below).
    let (code, om) = http_get_accept(
        &address,
        "/metrics",
        "application/openmetrics-text; version=1.0.0",
    )
    .expect("scrape");
    assert_eq!(code, 200);
    assert!(
        om.contains("# TYPE guardian_model info") && om.trim_end().ends_with("# EOF"),
        "{om}"
    );
    // Nothing else on that port.
    assert_eq!(http_get(&address, "/").unwrap().0, 404);
    assert_eq!(http_get(&address, "/verdict/1").unwrap().0, 404);
}

#[test]
fn a_real_prometheus_scrapes_the_daemon() {
    let prometheus = tool("prometheus", "prometheus");
    let (s, d, _client) = setup_with_a_stop(harness::METRICS_ANY_PORT);
    let target = d.metrics_address();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("free port")
        .port();
    let dir = s.dir.path().join("prometheus");
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("prometheus.yml");
    std::fs::write(
        &config,
        format!(
            "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\nscrape_configs:\n  - job_name: guardiand\n    static_configs:\n      - targets: ['{target}']\n"
        ),
    )
    .unwrap();
    let _server = Killed(
        Command::new(&prometheus)
            .arg(format!("--config.file={}", config.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.join("data").display()
            ))
            .arg(format!("--web.listen-address=127.0.0.1:{port}"))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("log")).unwrap())
            .spawn()
            .expect("start prometheus"),
    );
    let api = format!("127.0.0.1:{port}");
    // Every class's series are pre-set to 0 per reason: the one that counted is above 0.
    let query =
        "/api/v1/query?query=guardian_checks_total%7Breason%3D%22wrong-task%22%7D%20%3E%200";
    let start = Instant::now();
    let series = loop {
        if let Ok((200, body)) = http_get(&api, query)
            && let Ok(v) = serde_json::from_str::<serde_json::Value>(&body)
            && let Some(first) = v["data"]["result"].as_array().and_then(|r| r.first())
        {
            break first.clone();
        }
        assert!(
            start.elapsed() < PATIENCE,
            "Prometheus never scraped the daemon:\n{}",
            std::fs::read_to_string(dir.join("log")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(250));
    };
    assert_eq!(series["metric"]["class"], "task2", "{series}");
    assert_eq!(series["metric"]["job"], "guardiand", "{series}");
    assert_eq!(series["value"][1], "1", "{series}");
    // The scrape itself is healthy.
    let (_, up) = http_get(&api, "/api/v1/query?query=up").expect("query up");
    assert!(up.contains("\"1\""), "{up}");
}

#[test]
fn the_page_shows_a_stopped_plan_beside_its_class_in_chromium() {
    let chromium = tool("chromium", "chromium");
    let tables = format!(
        "{}[web]\naddress = \"127.0.0.1:0\"\n",
        harness::METRICS_ANY_PORT
    );
    let (s, d, _client) = setup_with_a_stop(&tables);
    let id = no_go_rows(&s)[0]["id"].as_i64().expect("id");
    let page = d.page_address();
    // Read-only: no write operations.
    assert_eq!(http_get(&page, "/nothing").unwrap().0, 404);

    // The umask chromium inherits: with 0177 it cannot use the directories it creates
    // and dies at start (it did while two test threads' client connects could leave the
    // process at 0177; `Client::connect` now takes turns).
    let umask = || {
        std::fs::read_to_string("/proc/self/status")
            .unwrap_or_default()
            .lines()
            .find(|l| l.starts_with("Umask:"))
            .unwrap_or("Umask: ?")
            .to_owned()
    };
    let browser = |args: &[String]| {
        let profile = tempfile::tempdir().expect("profile dir");
        let mut cmd = Command::new(&chromium);
        cmd.args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .args(args);
        let (status, out, err) = run_bounded(cmd, Duration::from_secs(120));
        assert!(
            status.success(),
            "chromium failed (this process's {}): {err}",
            umask()
        );
        out
    };
    // The front page lists the stop and links to it.
    let front = browser(&["--dump-dom".into(), format!("http://{page}/")]);
    assert!(
        front.contains(&format!("href=\"/verdict/{id}\"")),
        "front page:\n{front}"
    );
    // The stop's page: the plan's pen path, the claimed class's and the nearest class's
    // enrolled examples, each an SVG with strokes, as the browser built the document.
    let dom = browser(&["--dump-dom".into(), format!("http://{page}/verdict/{id}")]);
    for svg in ["stopped-plan", "claimed-class", "nearest-class"] {
        let at = dom
            .find(&format!("<svg id=\"{svg}\""))
            .unwrap_or_else(|| panic!("no {svg} drawing:\n{dom}"));
        let end = at + dom[at..].find("</svg>").expect("svg end");
        let strokes = dom[at..end].matches("<polyline class=\"stroke\"").count();
        assert!(strokes >= 1, "{svg} has no strokes:\n{}", &dom[at..end]);
    }
    assert!(dom.contains("claimed class task2") && dom.contains("nearest class task1"));
    // A screenshot (docs/img/page-no-go.png was taken like this).
    let shot = s.dir.path().join("page.png");
    browser(&[
        format!("--screenshot={}", shot.display()),
        "--window-size=1000,720".into(),
        format!("http://{page}/verdict/{id}"),
    ]);
    let png = std::fs::read(&shot).expect("screenshot written");
    assert!(png.starts_with(b"\x89PNG"), "not a PNG");
    if let Ok(keep) = std::env::var("GUARDIAN_PAGE_SCREENSHOT") {
        std::fs::copy(&shot, keep).expect("keep the screenshot");
    }
}
