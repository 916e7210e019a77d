//! The read-only page (`[web] address`, off unless set; `docs/operating.md`, "What the
//! screen stops"): status, classes and recent verdicts; a no-go opens to its plan's pen
//! path drawn beside the enrolled examples of the claimed class and of the nearest class
//! (SVG).
//!
//! It is an opt-in part of the daemon, on its own thread and address, and reads only files:
//! the verdict record (SQLite, read-only) and the persisted bank (snapshot and journal, the
//! state every acknowledged change is in). It never touches the serving loop's state, so
//! the check path neither carries nor waits for it. It has no write operations: every
//! method but GET and HEAD is refused.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use guardian_bank::{Class, ClassBank};
use guardian_robot::kinematics::Robot;
use guardian_shared::trajectory::{TOOL, Waypoint, split_flat};

use crate::config::Config;

/// How many recent verdicts the front page lists.
const RECENT: usize = 50;
/// How many enrolled examples of a class a verdict page draws.
const EXAMPLES_DRAWN: usize = 5;

/// Which verdicts the front page lists: only no-go (`?no-go`), and those before a verdict
/// id (`?before=ID`, the "older" link: [`RECENT`] a page).
#[derive(Debug, Clone, Copy, Default)]
struct Listing {
    no_go: bool,
    before: Option<i64>,
}

/// What the page reads.
struct Page {
    record: PathBuf,
    bank: PathBuf,
    /// The bank served while the state directory holds none (the shipped default bank).
    default_bank: Option<PathBuf>,
    robot: Robot,
    service: String,
}

/// Serve the page on its own thread if `[web] address` is set; a bind failure is logged
/// and the daemon serves without it.
pub fn start(
    config: &Config,
    robot: Robot,
    stop: &Arc<AtomicBool>,
) -> Option<std::thread::JoinHandle<()>> {
    let address = config.web.address.as_deref()?.trim().to_owned();
    let server = match crate::http::Listener::bind(&address) {
        Ok(s) => s,
        Err(e) => {
            tracing::error!(address, error = %e, "cannot serve the page; serving checks without it");
            return None;
        }
    };
    let bound = server.address();
    tracing::info!(address = %bound, "page served at http://{bound}/");
    let page = Page {
        record: config.record_path(),
        bank: config.bank_path(),
        default_bank: config.default_bank_path(),
        robot,
        service: config.service_name.clone(),
    };
    let stop = stop.clone();
    std::thread::Builder::new()
        .name("page".into())
        .spawn(move || page.serve(server, &stop))
        .map_err(|e| tracing::error!(error = %e, "cannot start the page thread"))
        .ok()
}

/// One verdict row of the record.
struct Row {
    id: i64,
    time_ms: i64,
    claimed: String,
    verdict: String,
    reason: String,
    distance: Option<f64>,
    threshold: Option<f64>,
    margin: Option<f64>,
    nearest: Vec<(String, Option<f64>)>,
    model: String,
    bank_version: i64,
    client: String,
}

const COLUMNS: &str = "id, time_ms, claimed, verdict, reason, distance, threshold, margin, nearest, model, bank_version, client, message";

fn row(r: &rusqlite::Row<'_>) -> rusqlite::Result<Row> {
    let nearest: String = r.get(8)?;
    let nearest = serde_json::from_str::<Vec<serde_json::Value>>(&nearest)
        .unwrap_or_default()
        .iter()
        .map(|v| {
            (
                v["class"].as_str().unwrap_or("").to_owned(),
                v["distance"].as_f64(),
            )
        })
        .collect();
    Ok(Row {
        id: r.get(0)?,
        time_ms: r.get(1)?,
        claimed: r.get(2)?,
        verdict: r.get(3)?,
        // The reason with why (the record's message: rule and waypoint, feature and
        // numbers), when there is one.
        reason: {
            let (reason, why): (String, String) = (r.get(4)?, r.get(12)?);
            if why.is_empty() {
                reason
            } else {
                format!("{reason}: {why}")
            }
        },
        distance: r.get(5)?,
        threshold: r.get(6)?,
        margin: r.get(7)?,
        nearest,
        model: r.get(9)?,
        bank_version: r.get(10)?,
        client: r.get(11)?,
    })
}

impl Page {
    fn serve(self, server: crate::http::Listener, stop: &AtomicBool) {
        crate::http::serve(server, stop, "page", move |request| {
            let path = request.path.as_str();
            let (code, body) = if !request.is_get() {
                (405, "read-only: GET only\n".to_owned())
            } else if path == "/" {
                self.front(&Listing {
                    no_go: request.param("no-go").is_some(),
                    before: request.param("before").and_then(|b| b.parse().ok()),
                })
            } else if let Some(id) = path
                .strip_prefix("/verdict/")
                .and_then(|i| i.parse::<i64>().ok())
            {
                self.verdict(id)
            } else {
                (404, "not found\n".to_owned())
            };
            let mut response = crate::http::Response::text(code, body);
            if code == 200 {
                response.content_type = "text/html; charset=utf-8";
            }
            response
        });
    }

    /// The bank the daemon serves: the state directory's, or, while there is none, the
    /// default bank it started from.
    fn bank(&self) -> Result<ClassBank, String> {
        match &self.default_bank {
            Some(default) if !self.bank.exists() => ClassBank::load(default),
            _ => ClassBank::load_with_journal(&self.bank).map(|(b, _)| b),
        }
        .map_err(|e| e.to_string())
    }

    /// Status, classes, recent verdicts.
    fn front(&self, listing: &Listing) -> (u16, String) {
        let mut out = head("guardian");
        let _ = write!(out, "<h1>guardian: {}</h1>", esc(&self.service));
        let bank = self.bank();
        out.push_str("<h2>Status</h2><table id=\"status\">");
        let _ = write!(
            out,
            "<tr><th>robot</th><td>{} ({} joints)</td></tr>",
            esc(self.robot.name()),
            self.robot.joints()
        );
        match &bank {
            Ok(b) => {
                let _ = write!(
                    out,
                    "<tr><th>model</th><td>{}</td></tr><tr><th>bank version</th><td>{}</td></tr><tr><th>classes</th><td>{}</td></tr>",
                    esc(b.model_version()),
                    b.generation(),
                    b.len()
                );
            }
            Err(e) => {
                let _ = write!(
                    out,
                    "<tr><th>bank</th><td>cannot read: {}</td></tr>",
                    esc(e)
                );
            }
        }
        let counts = self.with_record(|c| {
            let mut s = c.prepare(
                "SELECT verdict, COUNT(*) FROM verdicts WHERE time_ms >= ?1 GROUP BY verdict ORDER BY verdict",
            )?;
            let day = crate::record::now_ms() - 86_400_000;
            let rows = s.query_map([day], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))?;
            rows.collect::<rusqlite::Result<Vec<_>>>()
        });
        match counts {
            Ok(counts) => {
                let text: Vec<String> = counts.iter().map(|(v, n)| format!("{n} {v}")).collect();
                let _ = write!(
                    out,
                    "<tr><th>checks, last 24 h</th><td>{}</td></tr>",
                    esc(&if text.is_empty() {
                        "none".to_owned()
                    } else {
                        text.join(", ")
                    })
                );
            }
            Err(e) => {
                let _ = write!(
                    out,
                    "<tr><th>record</th><td>cannot read: {}</td></tr>",
                    esc(&e)
                );
            }
        }
        out.push_str("</table>");

        out.push_str(if listing.no_go {
            "<h2>Recent no-go verdicts</h2><p><a href=\"/\">all verdicts</a></p>"
        } else {
            "<h2>Recent verdicts</h2><p><a href=\"/?no-go\">only no-go</a></p>"
        });
        out.push_str("<table id=\"verdicts\"><tr><th>time (UTC)</th><th>claimed</th><th>verdict</th><th>reason</th><th>distance</th><th>threshold</th><th>nearest</th></tr>");
        let recent = self
            .with_record(|c| {
                let filter = if listing.no_go {
                    " AND verdict = 'no-go'"
                } else {
                    ""
                };
                let mut s = c.prepare(&format!(
                    "SELECT {COLUMNS} FROM verdicts WHERE id < ?1{filter} ORDER BY id DESC LIMIT {RECENT}"
                ))?;
                let rows = s.query_map([listing.before.unwrap_or(i64::MAX)], row)?;
                rows.collect::<rusqlite::Result<Vec<_>>>()
            })
            .unwrap_or_default();
        let older = (recent.len() == RECENT)
            .then(|| recent.last().map(|r| r.id))
            .flatten();
        for r in recent {
            let verdict = if r.verdict == "no-go" {
                format!("<a href=\"/verdict/{}\">no-go</a>", r.id)
            } else {
                esc(&r.verdict)
            };
            let _ = write!(
                out,
                "<tr class=\"{}\"><td>{}</td><td>{}</td><td>{verdict}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                esc(&r.verdict),
                utc(r.time_ms),
                esc(&r.claimed),
                esc(&r.reason),
                num(r.distance),
                num(r.threshold),
                esc(&r.nearest.first().map(|n| n.0.clone()).unwrap_or_default())
            );
        }
        out.push_str("</table>");
        if let Some(id) = older {
            let _ = write!(
                out,
                "<p><a id=\"older\" href=\"/?{}before={id}\">older</a></p>",
                if listing.no_go { "no-go&" } else { "" }
            );
        }

        out.push_str("<h2>Classes</h2><table id=\"classes\"><tr><th>class</th><th>examples</th><th>threshold</th></tr>");
        if let Ok(b) = &bank {
            for (name, class) in b.classes() {
                let _ = write!(
                    out,
                    "<tr><td>{}</td><td>{}</td><td>{}</td></tr>",
                    esc(name),
                    class.embeddings.len(),
                    num(b.threshold(name).map(f64::from))
                );
            }
        }
        out.push_str("</table></body></html>\n");
        (200, out)
    }

    /// One verdict: its figures, and for a no-go its plan beside the claimed and the
    /// nearest class.
    fn verdict(&self, id: i64) -> (u16, String) {
        let found = self.with_record(|c| {
            let v = c.query_row(
                &format!("SELECT {COLUMNS} FROM verdicts WHERE id = ?1"),
                [id],
                row,
            )?;
            let plan = c
                .query_row(
                    "SELECT channels, vals FROM plans WHERE verdict_id = ?1",
                    [id],
                    |r| Ok((r.get::<_, i64>(0)?, r.get::<_, Vec<u8>>(1)?)),
                )
                .ok();
            Ok((v, plan))
        });
        let (v, plan) = match found {
            Ok(f) => f,
            Err(e) => return (404, format!("no verdict {id}: {e}\n")),
        };
        let mut out = head(&format!("verdict {id}"));
        let _ = write!(
            out,
            "<p><a href=\"/\">back</a></p><h1>Verdict {id}: {} ({})</h1><table id=\"verdict\">\
             <tr><th>time (UTC)</th><td>{}</td></tr><tr><th>claimed</th><td>{}</td></tr>\
             <tr><th>distance</th><td>{}</td></tr><tr><th>threshold</th><td>{}</td></tr>\
             <tr><th>margin</th><td>{}</td></tr><tr><th>nearest</th><td>{}</td></tr>\
             <tr><th>model</th><td>{}</td></tr><tr><th>bank version</th><td>{}</td></tr>\
             <tr><th>client</th><td>{}</td></tr></table>",
            esc(&v.verdict),
            esc(&v.reason),
            utc(v.time_ms),
            esc(&v.claimed),
            num(v.distance),
            num(v.threshold),
            num(v.margin),
            esc(&v
                .nearest
                .iter()
                .map(|(n, d)| format!("{n} ({})", num(*d)))
                .collect::<Vec<_>>()
                .join(", ")),
            esc(&v.model),
            v.bank_version,
            esc(&v.client),
        );
        let bank = self.bank().ok();
        let class = |name: &str| bank.as_ref().and_then(|b| b.class(name));
        let nearest_other = v
            .nearest
            .iter()
            .map(|(n, _)| n.as_str())
            .find(|n| *n != v.claimed);
        out.push_str("<div class=\"panels\">");
        match plan.and_then(|(channels, bytes)| self.plan_path(channels, &bytes)) {
            Some(path) => panel(
                &mut out,
                "stopped-plan",
                &format!("stopped plan (claimed {})", v.claimed),
                &[path],
                "#c0392b",
            ),
            None => out.push_str("<p id=\"no-plan\">no plan kept for this verdict</p>"),
        }
        self.class_panel(
            &mut out,
            "claimed-class",
            "claimed",
            &v.claimed,
            class(&v.claimed),
        );
        if let Some(n) = nearest_other {
            self.class_panel(&mut out, "nearest-class", "nearest", n, class(n));
        }
        out.push_str("</div></body></html>\n");
        (200, out)
    }

    fn class_panel(
        &self,
        out: &mut String,
        id: &str,
        what: &str,
        name: &str,
        class: Option<&Class>,
    ) {
        let paths: Vec<Vec<([f64; 2], bool)>> = class
            .map(|c| {
                c.examples
                    .iter()
                    .take(EXAMPLES_DRAWN)
                    .map(|e| self.pen_path(&e.to_resampled()))
                    .collect()
            })
            .unwrap_or_default();
        if paths.is_empty() {
            let _ = write!(
                out,
                "<p id=\"{id}\">{what} class {}: not enrolled, or enrolled without its plans</p>",
                esc(name)
            );
            return;
        }
        panel(
            out,
            id,
            &format!("{what} class {name}: {} enrolled examples", paths.len()),
            &paths,
            "#2c3e50",
        );
    }

    /// The pen path of a plan as sent (`channels` wide, little-endian `f32`).
    fn plan_path(&self, channels: i64, bytes: &[u8]) -> Option<Vec<([f64; 2], bool)>> {
        let values: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let waypoints = split_flat(
            &values,
            usize::try_from(channels).ok()?,
            self.robot.joints(),
        )
        .ok()?;
        let path = self.pen_path(&waypoints);
        (!path.is_empty()).then_some(path)
    }

    /// Pen-tip positions in the canvas plane (base x, y), with pen down or up.
    fn pen_path(&self, waypoints: &[Waypoint]) -> Vec<([f64; 2], bool)> {
        let finite: Vec<Waypoint> = waypoints
            .iter()
            .filter(|w| w.iter().all(|v| v.is_finite()))
            .copied()
            .collect();
        let mut xyz = vec![[0.0f64; 3]; finite.len()];
        self.robot.pen_tip_positions_into(&finite, &mut xyz);
        xyz.iter()
            .zip(&finite)
            .map(|(p, w)| ([p[0], p[1]], w[TOOL] > 0.5))
            .collect()
    }

    fn with_record<T>(
        &self,
        f: impl FnOnce(&rusqlite::Connection) -> rusqlite::Result<T>,
    ) -> Result<T, String> {
        crate::record::open_read_only(&self.record)
            .and_then(|c| f(&c))
            .map_err(|e| e.to_string())
    }
}

/// An SVG panel: each path's pen-down strokes, seen from above (base +x up, +y left, as
/// the drawing is seen on the canvas), scaled together to fit.
fn panel(out: &mut String, id: &str, title: &str, paths: &[Vec<([f64; 2], bool)>], colour: &str) {
    const SIZE: f64 = 240.0;
    const PAD: f64 = 12.0;
    let points = paths.iter().flatten().map(|(p, _)| p);
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for p in points {
        for i in 0..2 {
            lo[i] = lo[i].min(p[i]);
            hi[i] = hi[i].max(p[i]);
        }
    }
    let span = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-6);
    let scale = (SIZE - 2.0 * PAD) / span;
    // Screen x grows with -y (base), screen y grows with -x (base).
    let map = |p: &[f64; 2]| (PAD + (hi[1] - p[1]) * scale, PAD + (hi[0] - p[0]) * scale);
    let _ = write!(
        out,
        "<figure><svg id=\"{id}\" xmlns=\"http://www.w3.org/2000/svg\" width=\"{SIZE}\" height=\"{SIZE}\" viewBox=\"0 0 {SIZE} {SIZE}\"><rect width=\"{SIZE}\" height=\"{SIZE}\" fill=\"#fafafa\" stroke=\"#ccc\"/>"
    );
    for (k, path) in paths.iter().enumerate() {
        let opacity = if paths.len() > 1 { 0.55 } else { 1.0 };
        let mut stroke: Vec<(f64, f64)> = Vec::new();
        let flush = |stroke: &mut Vec<(f64, f64)>, out: &mut String| {
            if stroke.len() >= 2 {
                let pts: Vec<String> = stroke
                    .iter()
                    .map(|(x, y)| format!("{x:.1},{y:.1}"))
                    .collect();
                let _ = write!(
                    out,
                    "<polyline class=\"stroke\" data-example=\"{k}\" points=\"{}\" fill=\"none\" stroke=\"{colour}\" stroke-opacity=\"{opacity}\" stroke-width=\"2\" stroke-linecap=\"round\"/>",
                    pts.join(" ")
                );
            }
            stroke.clear();
        };
        for (p, down) in path {
            if *down {
                stroke.push(map(p));
            } else {
                flush(&mut stroke, out);
            }
        }
        flush(&mut stroke, out);
    }
    let _ = write!(
        out,
        "</svg><figcaption>{}</figcaption></figure>",
        esc(title)
    );
}

fn head(title: &str) -> String {
    format!(
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{}</title><style>\
         body{{font-family:sans-serif;margin:1.5em;color:#222}}table{{border-collapse:collapse}}\
         td,th{{padding:2px 8px;border-bottom:1px solid #ddd;text-align:left}}\
         tr.no-go td{{color:#c0392b}}.panels{{display:flex;gap:1em;flex-wrap:wrap}}\
         figure{{margin:0}}figcaption{{font-size:90%;max-width:240px}}</style></head><body>",
        esc(title)
    )
}

fn num(v: Option<f64>) -> String {
    v.map_or_else(|| "-".to_owned(), |v| format!("{v:.4}"))
}

/// `YYYY-MM-DD HH:MM:SS` (UTC) of a Unix time in milliseconds.
fn utc(ms: i64) -> String {
    let secs = ms.div_euclid(1000);
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02}",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

/// HTML-escape text.
fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fresh_daemon_shows_the_default_bank_it_serves() {
        let dir = tempfile::tempdir().unwrap();
        let default = dir.path().join("default.gcb");
        let mut b = ClassBank::new(2, "m", 0.5);
        b.enroll("Greek/character01", &[vec![1.0, 0.0]]).unwrap();
        b.save(&default).unwrap();
        let page = Page {
            record: dir.path().join("state/verdicts.sqlite"),
            bank: dir.path().join("state/bank.gcb"),
            default_bank: Some(default),
            robot: guardian_robot::kinematics::default_panda().clone(),
            service: "s".into(),
        };
        let (code, html) = page.front(&Listing::default());
        assert_eq!(code, 200);
        assert!(!html.contains("<th>bank</th>"), "{html}");
        assert!(html.contains("<th>classes</th><td>1</td>"), "{html}");
        assert!(html.contains("Greek/character01"), "{html}");
    }

    /// The index lists only no-go verdicts on `?no-go`, and pages back with `?before=`.
    #[test]
    fn the_index_filters_no_go_and_pages() {
        let dir = tempfile::tempdir().unwrap();
        let record = dir.path().join("verdicts.sqlite");
        let conn = rusqlite::Connection::open(&record).unwrap();
        conn.execute_batch(crate::record::SCHEMA).unwrap();
        // 240 verdicts, every other one a no-go: 120 no-go.
        for i in 0..240i64 {
            let verdict = if i % 2 == 0 { "go" } else { "no-go" };
            conn.execute(
                "INSERT INTO verdicts (time_ms, service, client, claimed, status, verdict, reason, message, distance, threshold, margin, gap, nearest, model, bank_version)
                 VALUES (?1, 's', 'c', 'task', 'ok', ?2, 'outlier', '', NULL, NULL, NULL, NULL, '[]', 'm', 1)",
                rusqlite::params![i, verdict],
            )
            .unwrap();
        }
        drop(conn);
        let page = Page {
            record,
            bank: dir.path().join("bank.gcb"),
            default_bank: None,
            robot: guardian_robot::kinematics::default_panda().clone(),
            service: "s".into(),
        };
        let rows =
            |html: &str, class: &str| html.matches(&format!("<tr class=\"{class}\">")).count();
        let (_, all) = page.front(&Listing::default());
        assert_eq!((rows(&all, "go"), rows(&all, "no-go")), (25, 25));
        let (_, no_go) = page.front(&Listing {
            no_go: true,
            before: None,
        });
        assert_eq!((rows(&no_go, "go"), rows(&no_go, "no-go")), (0, RECENT));
        // The newest no-go is id 240; the page's last is 142: older ones follow it.
        assert!(no_go.contains("href=\"/?no-go&before=142\""), "{no_go}");
        let (_, older) = page.front(&Listing {
            no_go: true,
            before: Some(142),
        });
        assert_eq!(rows(&older, "no-go"), RECENT);
        assert!(older.contains("/verdict/140\"") && !older.contains("/verdict/142\""));
        // The last page has no "older" link.
        let (_, last) = page.front(&Listing {
            no_go: true,
            before: Some(42),
        });
        assert_eq!(rows(&last, "no-go"), 20);
        assert!(!last.contains("id=\"older\""));
    }

    #[test]
    fn utc_dates_and_escaping() {
        assert_eq!(utc(0), "1970-01-01 00:00:00");
        assert_eq!(utc(1_796_470_496_000), "2026-12-05 11:34:56");
        assert_eq!(esc("<a&\"b'>"), "&lt;a&amp;&quot;b&#39;&gt;");
    }
}
