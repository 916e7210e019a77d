//! Write an untrained (random-weight) embedder to try `guardiand` before a trained model
//! ships: `cargo run -p guardian-daemon --example random_model -- /tmp/model.safetensors`.
//! Verdicts from it are meaningless beyond the protocol.
#![forbid(unsafe_code)]

fn main() -> anyhow::Result<()> {
    let path = std::env::args()
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("usage: random_model OUT.safetensors [SEED]"))?;
    let seed = std::env::args()
        .nth(2)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(1);
    let e = guardian_models::embedder::Embedder::random(seed);
    e.save(std::path::Path::new(&path))?;
    println!("wrote {path} (version {})", e.version());
    Ok(())
}
