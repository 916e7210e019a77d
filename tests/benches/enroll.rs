//! Enrollment cost against the bank's size, all figures from one run, at 64, 1,000 and 4,000
//! classes (5 examples each, as the shipped bank):
//!
//! - persisting one enrollment in this process, before and after the journal: the full
//!   rewrite every enroll used to do (`ClassBank::save`: temporary file, fsync, rename,
//!   fsync of the directory) against the journal append (`ClassBank::append_change`: one
//!   record, fdatasync), time and bytes written;
//! - the whole enrollment through a real `guardiand` and its admin socket (embedding 5
//!   examples, limits, journal append, answer), and the journal bytes it wrote.
//!
//! Run: `cargo bench -p guardian-tests --bench enroll`
//! Options after `--`: `--enrolls N` (per bank size, default 20).

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use guardian_bank::{ClassBank, journal_path};
use guardian_client::AdminClient;
use guardian_tests::harness::{Daemon, Setup, random_bank, traj};

/// A bank for `model` with `n` classes of 5 pseudo-random embeddings each.
fn bank_of(model: &Path, n: usize, seed: u64) -> ClassBank {
    random_bank(model, n, 5, seed)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn max(v: &[f64]) -> f64 {
    v.iter().copied().fold(0.0, f64::max)
}

fn main() -> Result<()> {
    let mut enrolls = 20usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--enrolls" => enrolls = args.next().unwrap_or_default().parse()?,
            "--bench" => {}
            other => bail!("unknown option {other}"),
        }
    }
    println!(
        "guardian enrollment benchmark ({enrolls} enrollments per bank size, 5 examples each)"
    );
    println!();
    println!(
        "{:>7} {:>12} | {:>12} {:>12} | {:>12} {:>12} | {:>12} {:>12} {:>12}",
        "classes",
        "snapshot B",
        "rewrite ms",
        "rewrite B",
        "append ms",
        "append B",
        "e2e p50 ms",
        "e2e max ms",
        "journal B"
    );
    for n in [64usize, 1000, 4000] {
        let s = Setup::new(80 + n as u64);
        let state = s.state_dir();
        std::fs::create_dir_all(&state)?;
        let path = state.join("bank.gcb");
        let mut bank = bank_of(&s.model, n, 0x9e37_79b9_7f4a_7c15);
        bank.save(&path)?;
        let snapshot = std::fs::metadata(&path)?.len();

        // In process: the same enrollments persisted both ways, on a scratch copy.
        let scratch = tempfile::tempdir()?;
        let spath = scratch.path().join("bank.gcb");
        bank.save(&spath)?;
        let extra = bank_of(&s.model, enrolls, 7);
        let (mut rewrite, mut append) = (Vec::new(), Vec::new());
        let (mut rewrite_bytes, mut append_bytes) = (0u64, 0u64);
        for (name, class) in extra.classes() {
            let name = format!("new-{name}");
            bank.enroll(&name, &class.embeddings)?;
            let t = Instant::now();
            bank.save(&spath)?;
            rewrite.push(t.elapsed().as_secs_f64() * 1e3);
            rewrite_bytes += std::fs::metadata(&spath)?.len();
            let before = std::fs::metadata(journal_path(&spath)).map_or(0, |m| m.len());
            let t = Instant::now();
            let after = bank.append_change(&spath, &name)?;
            append.push(t.elapsed().as_secs_f64() * 1e3);
            append_bytes += after - before;
        }

        // Through the daemon and its admin socket.
        let mut s = s;
        let socket = s.dir.path().join("admin.sock");
        s.extra =
            format!("default-threshold = 1e9\n[admin]\nseparation = true\nsocket = {socket:?}\n");
        let d = Daemon::start(&s);
        let admin = AdminClient::new(&socket, Duration::from_secs(60));
        let mut e2e = Vec::new();
        for i in 0..enrolls {
            let examples: Vec<_> = (1..=5)
                .map(|dr| traj(i as u32 % 8, dr + i as u32))
                .collect();
            let t = Instant::now();
            admin
                .enroll(&format!("e2e{i:03}"), &examples)
                .map_err(|e| anyhow::anyhow!("enroll: {e}"))?;
            e2e.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let journal = std::fs::metadata(journal_path(&path)).map_or(0, |m| m.len());
        drop(d);
        println!(
            "{:>7} {:>12} | {:>12.2} {:>12} | {:>12.3} {:>12} | {:>12.2} {:>12.2} {:>12}",
            n,
            snapshot,
            median(rewrite.clone()),
            rewrite_bytes / enrolls as u64,
            median(append.clone()),
            append_bytes / enrolls as u64,
            median(e2e.clone()),
            max(&e2e),
            journal / enrolls as u64
        );
    }
    println!();
    println!("rewrite / append: medians of one enrollment's persistence (in process, same disk);");
    println!(
        "e2e: client-side enroll through the admin socket (embedding included); journal B: per enroll, header included"
    );
    Ok(())
}
