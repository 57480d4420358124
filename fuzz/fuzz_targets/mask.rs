//! Fuzz target `mask`: arbitrary bytes through [`clearview_fuzz::mask`] (see `fuzz/src/lib.rs`).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = clearview_fuzz::mask(data);
});
