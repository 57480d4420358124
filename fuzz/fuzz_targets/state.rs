//! Fuzz target `state`: arbitrary bytes through [`clearview_fuzz::state`] (see `fuzz/src/lib.rs`).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = clearview_fuzz::state(data);
});
