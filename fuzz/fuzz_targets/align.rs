//! Fuzz target `align`: arbitrary bytes through [`clearview_fuzz::align`] (see `fuzz/src/lib.rs`).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = clearview_fuzz::align(data);
});
