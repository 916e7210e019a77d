//! `guardian-lab fuse`: one model file of several trained networks (the branches of a fused
//! model, [`Embedder::fuse`]): e.g. a sequence network and a picture network of 64
//! dimensions each, whose embeddings the served model concatenates; or one model file
//! written again with other inference options (`--test-views`).

use std::path::PathBuf;

use guardian_models::embedder::Embedder;
use guardian_models::net::parse_test_views;

/// Arguments of `fuse`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The branch models, in embedding order (their embedding dimensions sum to at most
    /// 128; a fused model's branches count one by one).
    #[arg(required = true, num_args = 1..)]
    pub models: Vec<PathBuf>,
    /// The fused model file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Store every pen-feature branch without test-time reverse averaging (a branch keeps
    /// what its file says otherwise).
    #[arg(long)]
    pub no_reverse_average: bool,
    /// Test-time views of every pen-feature branch (see `guardian-lab eval --test-views`;
    /// `none` for none); without it a branch keeps what its file says.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub test_views: Option<Vec<String>>,
}

/// Load the branches, fuse them, write the model; print its version and architecture.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let mut parts = args
        .models
        .iter()
        .map(|p| Embedder::load(p).map_err(|e| anyhow::anyhow!("loading {}: {e}", p.display())))
        .collect::<anyhow::Result<Vec<_>>>()?;
    if args.no_reverse_average {
        parts.iter_mut().for_each(|p| p.set_reverse_average(false));
    }
    let mut fused = Embedder::fuse(&parts)?;
    if let Some(views) = &args.test_views {
        fused.set_test_views(&parse_test_views(views).map_err(anyhow::Error::msg)?)?;
    }
    fused.save(&args.out)?;
    println!(
        "{} {} ({} networks: {}): {}",
        args.out.display(),
        fused.version(),
        fused.nets().len(),
        parts
            .iter()
            .map(Embedder::version)
            .collect::<Vec<_>>()
            .join(" + "),
        fused.config_json()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_models::net::TestView;

    fn fuse_one(model: PathBuf, out: PathBuf, views: &[&str]) -> anyhow::Result<Embedder> {
        run(&Args {
            models: vec![model],
            out: out.clone(),
            no_reverse_average: false,
            test_views: Some(views.iter().map(|v| v.to_string()).collect()),
        })?;
        Ok(Embedder::load(&out)?)
    }

    #[test]
    fn one_model_is_written_again_with_test_views_and_without() {
        let dir = tempfile::tempdir().unwrap();
        let plain = dir.path().join("plain.safetensors");
        let model = Embedder::random(7);
        model.save(&plain).unwrap();
        let viewed = fuse_one(
            plain.clone(),
            dir.path().join("v.safetensors"),
            &["r200+x100", "r-200+x-100"],
        )
        .unwrap();
        let want: Vec<TestView> =
            vec!["r200+x100".parse().unwrap(), "r-200+x-100".parse().unwrap()];
        assert_eq!(viewed.configs()[0].test_views, want);
        assert_eq!(viewed.checksum(), model.checksum());
        assert_ne!(viewed.version(), model.version());
        let back = fuse_one(
            dir.path().join("v.safetensors"),
            dir.path().join("b.safetensors"),
            &["none"],
        )
        .unwrap();
        assert!(back.configs()[0].test_views.is_empty());
        assert_eq!(back.version(), model.version());
        let err = fuse_one(plain, dir.path().join("bad.safetensors"), &["y5"]).unwrap_err();
        assert!(err.to_string().contains("y5"), "{err}");
        assert!(!dir.path().join("bad.safetensors").exists());
    }
}
