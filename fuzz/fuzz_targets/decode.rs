//! Fuzz target `decode`: arbitrary bytes through [`clearview_fuzz::decode`] (see `fuzz/src/lib.rs`).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = clearview_fuzz::decode(data);
});
