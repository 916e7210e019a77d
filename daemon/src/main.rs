//! `guardiand`: thin entry point; everything lives in the `guardian_daemon` library.
#![forbid(unsafe_code)]

fn main() {
    eprintln!("guardiand: not implemented yet");
    std::process::exit(2);
}
