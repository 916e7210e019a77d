//! guardian-lab: the research bench behind guardian — Omniglot strokes to Panda joint
//! trajectories, training of the embedding network, baselines, few-shot evaluation and reports.
#![forbid(unsafe_code)]

fn main() {
    eprintln!("guardian-lab: no subcommands yet");
    std::process::exit(2);
}
