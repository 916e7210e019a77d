//! `guardianctl`: command-line access to a running `guardiand`.
#![forbid(unsafe_code)]

fn main() {
    eprintln!("guardianctl: not implemented yet");
    std::process::exit(2);
}
