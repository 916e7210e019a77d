//! `guardianctl verdicts` against hostile records and pipes, as a real process: `--json`
//! after the subcommand, a row whose time no calendar writes, ids aligned in the table, a
//! FIFO given as the record (refused, not read), and a reader that closes the pipe early
//! (the program ends without a panic).

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use guardian_daemon::record::SCHEMA;
use guardian_tests::harness;

/// A record with `n` no-go rows, the last one dated `i64::MAX` ms.
fn record(dir: &std::path::Path, n: i64) -> std::path::PathBuf {
    let path = dir.join("verdicts.sqlite");
    let conn = rusqlite::Connection::open(&path).unwrap();
    conn.execute_batch(SCHEMA).unwrap();
    for i in 0..n {
        let time = if i == n - 1 {
            i64::MAX
        } else {
            1_765_000_000_000 + i
        };
        conn.execute(
            "INSERT INTO verdicts (time_ms, service, client, claimed, status, verdict, reason, message, distance, threshold, margin, gap, nearest, model, bank_version)
             VALUES (?1, 's', 'c', 'task', 'ok', 'no-go', 'workcell', 'KeepOut at waypoint 3', NULL, NULL, NULL, NULL, '[]', 'm', 1)",
            [time],
        )
        .unwrap();
    }
    path
}

#[test]
fn json_after_the_subcommand_and_a_time_past_9999() {
    let dir = tempfile::tempdir().unwrap();
    let path = record(dir.path(), 12);
    let out = Command::new(harness::ctl_bin())
        .args(["verdicts", "--no-go", "--json", "--record"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(rows.len(), 12);
    assert_eq!(rows[11]["time"], format!("{} ms", i64::MAX));
    assert_eq!(rows[0]["message"], "KeepOut at waypoint 3");
    // The table: every id right-aligned in its column of 7.
    let out = Command::new(harness::ctl_bin())
        .args(["verdicts", "--record"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    for (line, id) in text.lines().skip(1).zip(1..) {
        assert_eq!(&line[..7], format!("{id:>7}"), "{text}");
    }
}

#[test]
fn a_fifo_is_refused_and_a_closed_pipe_ends_quietly() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("fifo.sqlite");
    assert!(
        Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    let mut child = Command::new(harness::ctl_bin())
        .args(["verdicts", "--record"])
        .arg(&fifo)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if start.elapsed() > harness::PATIENCE {
            let _ = child.kill();
            panic!("guardianctl hangs on a FIFO");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
    assert!(!status.success());
    assert!(err.contains("not a regular file"), "{err}");

    // More rows than a pipe buffers, and a reader that is gone.
    let path = record(dir.path(), 3000);
    let mut child = Command::new(harness::ctl_bin())
        .args(["verdicts", "--limit", "3000", "--record"])
        .arg(&path)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let status = child.wait().unwrap();
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
    assert_ne!(status.code(), Some(101), "panicked: {err}");
    assert!(!err.contains("panicked"), "{err}");
}
