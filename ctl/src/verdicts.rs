//! `guardianctl verdicts`: the daemon's verdict record (`docs/operating.md`, "What the
//! screen stops"), read-only, straight from its SQLite file (WAL: read beside the running
//! daemon). The schema is `guardian_daemon::record::SCHEMA`.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use anyhow::{Context, bail};
use rusqlite::{OpenFlags, params_from_iter, types::Value};

/// The record used when `--record` is not given: the packaged daemon's, else the quick
/// start's (`./guardiand-state`).
pub fn default_path() -> PathBuf {
    let system = Path::new("/var/lib/guardian/verdicts.sqlite");
    if system.exists() {
        return system.to_owned();
    }
    PathBuf::from("guardiand-state/verdicts.sqlite")
}

/// `--since`: an RFC 3339 time (`2026-12-05T10:00:00Z`) or a duration back from now
/// (`2h`, `30min`, `1day`). Milliseconds since the Unix epoch.
pub fn parse_since(text: &str) -> anyhow::Result<i64> {
    let at = match humantime::parse_rfc3339_weak(text) {
        Ok(t) => t,
        Err(_) => {
            let back = humantime::parse_duration(text).with_context(|| {
                format!(
                    "--since {text:?}: neither a time (2026-12-05T10:00:00Z) nor a duration (2h)"
                )
            })?;
            SystemTime::now()
                .checked_sub(back)
                .unwrap_or(SystemTime::UNIX_EPOCH)
        }
    };
    let ms = at
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or(Duration::ZERO)
        .as_millis();
    Ok(i64::try_from(ms).unwrap_or(i64::MAX))
}

/// Which verdicts to list.
#[derive(Debug)]
pub struct Filter {
    pub no_go: bool,
    pub class: Option<String>,
    pub since_ms: Option<i64>,
    pub limit: usize,
}

/// List the verdicts of the record at `path`, newest last.
pub fn list(path: &Path, filter: &Filter, json: bool) -> anyhow::Result<()> {
    if !path.exists() {
        bail!(
            "no verdict record at {} (the daemon's state directory; --record names another)",
            path.display()
        );
    }
    // A FIFO or a device would block SQLite's read: only a regular file is a record.
    if !std::fs::metadata(path).is_ok_and(|m| m.is_file()) {
        bail!(
            "{} is not a regular file, so not a verdict record",
            path.display()
        );
    }
    let conn = rusqlite::Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY)
        .with_context(|| format!("cannot open the verdict record {}", path.display()))?;
    conn.busy_timeout(Duration::from_secs(2))?;
    let mut clauses = Vec::new();
    let mut args: Vec<Value> = Vec::new();
    if filter.no_go {
        clauses.push("verdict = 'no-go'".to_owned());
    }
    if let Some(c) = &filter.class {
        args.push(Value::Text(c.clone()));
        clauses.push(format!("claimed = ?{}", args.len()));
    }
    if let Some(t) = filter.since_ms {
        args.push(Value::Integer(t));
        clauses.push(format!("time_ms >= ?{}", args.len()));
    }
    let filter_sql = if clauses.is_empty() {
        String::new()
    } else {
        format!("WHERE {}", clauses.join(" AND "))
    };
    let sql = format!(
        "SELECT * FROM (SELECT v.id, v.time_ms, v.claimed, v.verdict, v.reason, v.message, v.distance, v.threshold, v.margin, v.nearest, v.model, v.bank_version, v.service, v.client, p.verdict_id IS NOT NULL, v.gap
         FROM verdicts v LEFT JOIN plans p ON p.verdict_id = v.id {filter_sql} ORDER BY v.id DESC LIMIT {}) ORDER BY id",
        filter.limit
    );
    let mut stmt = conn
        .prepare(&sql)
        .map_err(|e| match e.sqlite_error_code() {
            Some(rusqlite::ErrorCode::DatabaseBusy | rusqlite::ErrorCode::DatabaseLocked) => {
                anyhow::anyhow!(
                    "the verdict record {} is locked by another process (2 s waited); try again",
                    path.display()
                )
            }
            _ => {
                anyhow::Error::new(e).context(format!("{} is not a verdict record", path.display()))
            }
        })?;
    let rows = stmt.query_map(params_from_iter(args), |r| {
        let nearest: String = r.get(9)?;
        Ok(serde_json::json!({
            "id": r.get::<_, i64>(0)?,
            "time": rfc3339(r.get(1)?),
            "claimed": r.get::<_, String>(2)?,
            "verdict": r.get::<_, String>(3)?,
            "reason": r.get::<_, String>(4)?,
            "message": r.get::<_, String>(5)?,
            "distance": r.get::<_, Option<f64>>(6)?,
            "threshold": r.get::<_, Option<f64>>(7)?,
            "margin": r.get::<_, Option<f64>>(8)?,
            "nearest": serde_json::from_str::<serde_json::Value>(&nearest).unwrap_or_default(),
            "model": r.get::<_, String>(10)?,
            "bank_version": r.get::<_, i64>(11)?,
            "service": r.get::<_, String>(12)?,
            "client": r.get::<_, String>(13)?,
            "plan_kept": r.get::<_, bool>(14)?,
            "gap": r.get::<_, Option<f64>>(15)?,
        }))
    })?;
    let rows = rows.collect::<Result<Vec<_>, _>>()?;
    if json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
        return Ok(());
    }
    println!(
        "{:>7} {:<20} {:<24} {:<6} {:<18} {:>8} {:>9} {:<24} plan",
        "id", "time (UTC)", "claimed", "verdict", "reason", "distance", "threshold", "nearest"
    );
    let num = |v: &serde_json::Value| v.as_f64().map_or("-".to_owned(), |x| format!("{x:.4}"));
    for r in &rows {
        let nearest = r["nearest"]
            .as_array()
            .and_then(|a| a.first())
            .and_then(|n| n["class"].as_str())
            .unwrap_or("-");
        println!(
            "{:>7} {:<20} {:<24} {:<6} {:<18} {:>8} {:>9} {:<24} {}",
            r["id"].as_i64().unwrap_or(0),
            r["time"]
                .as_str()
                .unwrap_or("")
                .replace('T', " ")
                .trim_end_matches('Z'),
            r["claimed"].as_str().unwrap_or(""),
            r["verdict"].as_str().unwrap_or(""),
            r["reason"].as_str().unwrap_or(""),
            num(&r["distance"]),
            num(&r["threshold"]),
            nearest,
            if r["plan_kept"].as_bool() == Some(true) {
                "kept"
            } else {
                "-"
            }
        );
    }
    Ok(())
}

/// An RFC 3339 time, or `<ms> ms` for a time RFC 3339 cannot write (before 1970, after
/// 9999: a row written by a clock gone wrong).
fn rfc3339(ms: i64) -> String {
    const LAST: u64 = 253_402_300_799_000; // 9999-12-31T23:59:59Z
    match u64::try_from(ms) {
        Ok(v) if v <= LAST => {
            humantime::format_rfc3339_seconds(SystemTime::UNIX_EPOCH + Duration::from_millis(v))
                .to_string()
        }
        _ => format!("{ms} ms"),
    }
}

#[cfg(test)]
mod tests {
    use super::rfc3339;

    #[test]
    fn every_time_a_row_can_hold_prints() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00Z");
        assert_eq!(rfc3339(253_402_300_799_000), "9999-12-31T23:59:59Z");
        assert_eq!(rfc3339(i64::MAX), format!("{} ms", i64::MAX));
        assert_eq!(rfc3339(-5), "-5 ms");
    }
}
