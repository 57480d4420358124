//! clearview: removes trees, cars and people from photographs of buildings by filling the
//! hole with what other photographs of the same facade actually saw there.
//!
//! # Layout
//!
//! ```text
//!             sources (async)            compute (sync, CPU-bound)           sinks (async)
//!   folder watch ─┐                 ┌───────────────────────────┐
//!                 ├─► decoded View ─►  Session::add_view(view)  ├─► Update ─► result files,
//!   video frames ─┘   (channel)     │   align → warp → fill      │   (channel)  sidecar JSON,
//!                                   └───────────────────────────┘              events, HTTP
//! ```
//!
//! The core is pure (no I/O, no clock, seeded randomness):
//! - [`imaging`]: image planes, decoding from bytes, filters, pyramids;
//! - [`features`]: Harris corners and oriented, normalised patch descriptors, matching;
//! - [`geometry`]: homographies, the normalised DLT, robust estimation (LMedS, MSAC);
//! - [`align`]: the pipeline that turns a keyframe and a view into a verdict and an `H`;
//! - [`inpaint`]: the fill of the keyframe's masked region from the aligned views;
//! - [`session`]: one keyframe, its mask, a bounded buffer of cropped aligned views, the
//!   rule that decides when a new view is worth a fill, and the current result.
//!
//! The shell, [`daemon`], is asynchronous and owns all I/O and time: it watches the
//! upload folder, decodes complete files, hands work to a fixed set of compute threads
//! (each owning some sessions), writes results atomically, logs events, saves state and
//! talks to systemd.
//!
//! The edges (`main.rs`, [`cli`], [`config`]) parse arguments and TOML, read files and
//! print; [`fsio`] is their and the service's crash-safe file write.

/// The seed of every random choice unless told otherwise: the one-shot fill, the service
/// and the alignment share it, so that they make the same result of the same views.
pub const DEFAULT_SEED: u64 = 0x00c1_ea4e;

pub mod align;
pub mod cli;
pub mod config;
pub mod daemon;
pub mod features;
pub mod fsio;
pub mod geometry;
pub mod imaging;
pub mod inpaint;
pub mod session;
pub mod synth;
