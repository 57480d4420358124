//! Lossy WebP results (pure layer: pixels and metadata in, bytes out): libwebp's VP8
//! encoder through the `webp` crate, then libwebp's mux (through `libwebp-sys`) to put the
//! colour profile, EXIF and XMP in their RIFF chunks (`VP8X` extended header, `ICCP`,
//! `EXIF`, `XMP `). Lossless WebP goes through `image-webp` in [`super::encode`].

use std::ffi::CStr;

use libwebp_sys::{
    WEBP_MUX_ABI_VERSION, WebPData, WebPFree, WebPMux, WebPMuxAssemble, WebPMuxCreateInternal, WebPMuxDelete,
    WebPMuxError, WebPMuxSetChunk,
};
use thiserror::Error;

/// Largest side of a WebP image (14 bits in the bitstream's header).
pub const MAX_SIDE: usize = 16383;

/// Why a lossy WebP could not be made.
#[derive(Debug, Error)]
pub enum WebPError {
    #[error("{width}x{height} is too large for WebP (at most {MAX_SIDE} pixels a side)")]
    TooLarge { width: usize, height: usize },
    #[error("libwebp's encoder failed: {0:?}")]
    Encoder(libwebp_sys::WebPEncodingError),
    #[error("libwebp's configuration was refused")]
    Config,
    #[error("libwebp's mux failed on {what}: {error:?}")]
    Mux { what: &'static str, error: WebPMuxError },
}

/// A metadata chunk of a WebP file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Chunk {
    /// The ICC profile (`ICCP`).
    Icc,
    /// EXIF as a TIFF structure, without JPEG's `Exif\0\0` signature (`EXIF`).
    Exif,
    /// The XMP packet (`XMP `).
    Xmp,
}

impl Chunk {
    fn fourcc(self) -> &'static CStr {
        match self {
            Chunk::Icc => c"ICCP",
            Chunk::Exif => c"EXIF",
            Chunk::Xmp => c"XMP ",
        }
    }
}

/// `rgb` (8-bit, interleaved, `width × height`) as a lossy WebP file at `quality` (1 to 100,
/// as libwebp's `-q`) carrying `chunks`.
pub fn encode_lossy(
    rgb: &[u8],
    width: usize,
    height: usize,
    quality: u8,
    chunks: &[(Chunk, &[u8])],
) -> Result<Vec<u8>, WebPError> {
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(WebPError::TooLarge { width, height });
    }
    assert_eq!(rgb.len(), 3 * width * height, "whole RGB pixels");
    let mut config = webp::WebPConfig::new().map_err(|()| WebPError::Config)?;
    config.quality = f32::from(quality.clamp(1, 100));
    // Method 4 (libwebp's default, and cwebp's): the usual balance of speed and size.
    config.method = 4;
    // VP8 stores chroma at half resolution: the sharp RGB → YUV conversion keeps colour
    // edges (a facade's window frames) where the plain one smears them.
    config.use_sharp_yuv = 1;
    let simple = webp::Encoder::from_rgb(rgb, width as u32, height as u32)
        .encode_advanced(&config)
        .map_err(WebPError::Encoder)?;
    if chunks.iter().all(|(_, data)| data.is_empty()) {
        return Ok(simple.to_vec());
    }
    let mux = Mux::of(&simple)?;
    for &(chunk, data) in chunks.iter().filter(|(_, d)| !d.is_empty()) {
        mux.set_chunk(chunk, data)?;
    }
    mux.assemble()
}

/// A libwebp mux, deleted when dropped. Every piece of data given to it is copied in
/// (`copy_data = 1`), so no borrow outlives a call.
struct Mux(*mut WebPMux);

fn data(bytes: &[u8]) -> WebPData {
    WebPData { bytes: bytes.as_ptr(), size: bytes.len() }
}

impl Mux {
    /// A mux holding the image of a simple (VP8) WebP file.
    fn of(file: &[u8]) -> Result<Self, WebPError> {
        let d = data(file);
        // SAFETY: `d` points into `file`, alive for the call; libwebp copies what it keeps.
        let ptr = unsafe { WebPMuxCreateInternal(&d, 1, WEBP_MUX_ABI_VERSION as i32) };
        if ptr.is_null() {
            return Err(WebPError::Mux { what: "the encoded image", error: WebPMuxError::WEBP_MUX_BAD_DATA });
        }
        Ok(Mux(ptr))
    }

    fn set_chunk(&self, chunk: Chunk, bytes: &[u8]) -> Result<(), WebPError> {
        let d = data(bytes);
        // SAFETY: the mux is live; the fourcc is a 4-character C string; `d` is copied.
        let e = unsafe { WebPMuxSetChunk(self.0, chunk.fourcc().as_ptr(), &d, 1) };
        match e {
            WebPMuxError::WEBP_MUX_OK => Ok(()),
            error => Err(WebPError::Mux { what: chunk_name(chunk), error }),
        }
    }

    /// The whole file: `VP8X` with the flags of the chunks present, then the chunks in the
    /// order the container specification sets.
    fn assemble(&self) -> Result<Vec<u8>, WebPError> {
        let mut out = WebPData { bytes: std::ptr::null(), size: 0 };
        // SAFETY: the mux is live; `out` receives a buffer libwebp allocated, freed below.
        let e = unsafe { WebPMuxAssemble(self.0, &mut out) };
        let bytes = if e == WebPMuxError::WEBP_MUX_OK && !out.bytes.is_null() {
            // SAFETY: libwebp returned `size` initialised bytes at `bytes`.
            Ok(unsafe { std::slice::from_raw_parts(out.bytes, out.size) }.to_vec())
        } else {
            Err(WebPError::Mux { what: "the file", error: e })
        };
        if !out.bytes.is_null() {
            // SAFETY: allocated by libwebp (WebPDataClear's body), not used after this.
            unsafe { WebPFree(out.bytes as *mut std::ffi::c_void) };
        }
        bytes
    }
}

fn chunk_name(chunk: Chunk) -> &'static str {
    match chunk {
        Chunk::Icc => "the ICC profile",
        Chunk::Exif => "the EXIF",
        Chunk::Xmp => "the XMP",
    }
}

impl Drop for Mux {
    fn drop(&mut self) {
        // SAFETY: created by WebPMuxCreateInternal, deleted once.
        unsafe { WebPMuxDelete(self.0) };
    }
}

/// The RIFF chunks of a WebP file, in order: four-character code and payload.
pub fn chunks(file: &[u8]) -> Vec<([u8; 4], &[u8])> {
    let mut out = Vec::new();
    if file.len() < 12 || &file[..4] != b"RIFF" || &file[8..12] != b"WEBP" {
        return out;
    }
    let mut i = 12;
    while let Some(head) = file.get(i..i + 8) {
        let fourcc = [head[0], head[1], head[2], head[3]];
        let len = u32::from_le_bytes([head[4], head[5], head[6], head[7]]) as usize;
        let Some(payload) = file.get(i + 8..i + 8 + len) else { break };
        out.push((fourcc, payload));
        i += 8 + len + (len & 1);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient(w: usize, h: usize) -> Vec<u8> {
        (0..w * h)
            .flat_map(|i| [(i % w * 255 / w) as u8, (i / w * 255 / h) as u8, ((i * 7) % 256) as u8])
            .collect()
    }

    #[test]
    fn a_lossy_file_carries_its_chunks_in_the_specified_order() {
        let rgb = gradient(64, 48);
        let icc = vec![7u8; 301];
        let exif = b"MM\0*\0\0\0\x08\0\0".to_vec();
        let xmp = b"<x:xmpmeta/>".to_vec();
        let file =
            encode_lossy(&rgb, 64, 48, 80, &[(Chunk::Exif, &exif), (Chunk::Xmp, &xmp), (Chunk::Icc, &icc)])
                .unwrap();
        let c = chunks(&file);
        let names: Vec<&[u8]> = c.iter().map(|(n, _)| n.as_slice()).collect();
        assert_eq!(names, [b"VP8X", b"ICCP", b"VP8 ", b"EXIF", b"XMP "].map(|n| n.as_slice()));
        assert_eq!(c[1].1, icc.as_slice());
        assert_eq!(c[3].1, exif.as_slice());
        assert_eq!(c[4].1, xmp.as_slice());
        // VP8X flags: ICC (0x20), EXIF (0x08), XMP (0x04); canvas 64x48 stored minus one.
        let vp8x = c[0].1;
        assert_eq!(vp8x[0], 0x20 | 0x08 | 0x04);
        assert_eq!((vp8x[4], vp8x[7]), (63, 47));
        let riff_len = u32::from_le_bytes(file[4..8].try_into().unwrap()) as usize;
        assert_eq!(riff_len + 8, file.len());
    }

    #[test]
    fn without_metadata_the_file_is_simple_and_sizes_are_checked() {
        let file = encode_lossy(&gradient(16, 16), 16, 16, 50, &[]).unwrap();
        let names: Vec<[u8; 4]> = chunks(&file).iter().map(|(n, _)| *n).collect();
        assert_eq!(names, [*b"VP8 "]);
        let big = encode_lossy(&[0; 3 * 16384], 16384, 1, 50, &[]);
        assert!(matches!(big, Err(WebPError::TooLarge { width: 16384, .. })), "{big:?}");
    }
}
