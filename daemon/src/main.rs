//! `guardiand`: thin entry point; everything lives in the `guardian_daemon` library.
#![forbid(unsafe_code)]

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use guardian_daemon::{Config, Control, run};
use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};

/// The guardian go/no-go screening daemon.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Config file (default: $GUARDIAN_CONFIG, else /etc/guardian/guardiand.toml if present).
    #[arg(long, short)]
    config: Option<PathBuf>,
    /// Print the default configuration as TOML and exit.
    #[arg(long)]
    print_default_config: bool,
    /// Check config, model and bank, then exit without serving.
    #[arg(long)]
    check: bool,
    /// Write a new fleet key pair (`docs/fleet.md`): the secret key to PATH (mode 0600,
    /// never overwritten) and the public key to PATH.pub, print the public key and exit.
    #[cfg(feature = "fleet")]
    #[arg(long, value_name = "PATH")]
    fleet_keygen: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    if args.print_default_config {
        print!("{}", Config::default_toml());
        return Ok(());
    }
    #[cfg(feature = "fleet")]
    if let Some(path) = &args.fleet_keygen {
        let public = guardian_fleet::keys::write_key_pair(path)?;
        println!("{}", guardian_fleet::keys::hex(public.as_bytes()));
        eprintln!(
            "secret key written to {} (mode 0600), public key to {}",
            path.display(),
            guardian_fleet::keys::public_path(path).display()
        );
        return Ok(());
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let (config, source) = Config::locate(args.config.as_deref())?;
    match &source {
        Some(p) => tracing::info!(config = %p.display(), "configuration loaded"),
        None => tracing::info!("no config file; using built-in defaults"),
    }
    if args.check {
        let (embedder, station) = guardian_daemon::state::load_model(&config)?;
        // A bank of another model is re-embedded in memory (and logged), not saved.
        let (bank, src) = guardian_daemon::state::load_bank_with(
            &config,
            &embedder,
            &station,
            guardian_daemon::state::Persist::No,
        )?;
        println!(
            "ok: model {} ({}), robot {} ({} joints), {} with {} classes",
            embedder.version(),
            config.model_path().display(),
            station.robot().name(),
            station.robot().joints(),
            src,
            bank.len()
        );
        for w in guardian_daemon::state::limit_warnings(&bank, &config.limits()) {
            println!("warning: configured limits below the loaded bank: {w}");
        }
        return Ok(());
    }
    let control = Control::default();
    for sig in [SIGTERM, SIGINT] {
        signal_hook::flag::register(sig, control.shutdown.clone())
            .with_context(|| format!("cannot install handler for signal {sig}"))?;
    }
    signal_hook::flag::register(SIGHUP, control.reload.clone())
        .context("cannot install SIGHUP handler")?;
    run(config, control).context("guardiand failed")?;
    Ok(())
}
