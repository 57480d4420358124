//! Every input kept under `tests/fuzz_regressions/<target>/` (crashes the fuzzers found,
//! and hand-made nasty inputs) run through the very function its fuzz target drives
//! (`fuzz/src/lib.rs`): each must end in `Ok` or a refusal in words, without a panic and
//! within a generous time.

#[path = "../fuzz/src/lib.rs"]
mod harness;

use std::path::PathBuf;
use std::sync::mpsc;
use std::time::Duration;

/// Far above what any input takes (milliseconds); only a hang gets near it.
const PER_INPUT: Duration = Duration::from_secs(60);

fn run_all(target: &str, f: fn(&[u8]) -> Result<(), String>) {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_regressions").join(target);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("a directory entry").path())
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no regression inputs in {}", dir.display());
    let mut failures = Vec::new();
    for path in files {
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(std::panic::catch_unwind(|| f(&bytes)));
        });
        let name = path.file_name().expect("a file name").to_string_lossy().into_owned();
        match rx.recv_timeout(PER_INPUT) {
            Ok(Ok(Ok(()))) => println!("{target}/{name}: ok"),
            Ok(Ok(Err(reason))) if !reason.trim().is_empty() => {
                println!("{target}/{name}: refused: {reason}")
            }
            Ok(Ok(Err(_))) => failures.push(format!("{name}: refused without a reason")),
            Ok(Err(_)) => failures.push(format!("{name}: panicked")),
            Err(_) => failures.push(format!("{name}: still running after {PER_INPUT:?}")),
        }
    }
    assert!(failures.is_empty(), "{target}: {failures:#?}");
}

#[test]
fn decode_inputs() {
    run_all("decode", harness::decode);
}

#[test]
fn align_inputs() {
    run_all("align", harness::align);
}

#[test]
fn config_inputs() {
    run_all("config", harness::config);
}

#[test]
fn mask_inputs() {
    run_all("mask", harness::mask);
}

#[test]
fn state_inputs() {
    run_all("state", harness::state);
}
