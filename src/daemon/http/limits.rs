//! What bounds the HTTP side's memory and connections under any mix of requests (shell
//! layer): a cap on event-stream subscribers, one image decoded at a time, a few request
//! bodies in memory at a time, and a small cache of view thumbnails.
//!
//! The ceiling that follows, with the defaults: [`MAX_DECODES`] decoded images (each at
//! most `watch.max_pixels` × 3 bytes, with its file's bytes) + [`MAX_BODIES`] request
//! bodies of at most `http.max_body_bytes` + [`THUMB_CACHE_BYTES`] of thumbnails + what
//! hyper keeps per connection (a few KiB, at most `MAX_CONNECTIONS` of them). Files are
//! streamed from disk, never read whole into memory to be served.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use axum::body::Bytes;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Event-stream (`/api/events`) subscribers at once; more are answered 503. Each holds a
/// connection for as long as it listens: without a cap, a few hundred of them took every
/// connection and `/healthz` stopped answering.
pub const MAX_EVENT_STREAMS: usize = 32;

/// Images the HTTP side decodes at once (thumbnails, painted masks); more wait their turn.
pub const MAX_DECODES: usize = 1;

/// Requests with a body (mask uploads, keyframe choices) held in memory at once; more are
/// answered 503.
pub const MAX_BODIES: usize = 4;

/// Bytes of thumbnails kept; the oldest go first.
pub const THUMB_CACHE_BYTES: usize = 8 << 20;

/// A file's identity for the thumbnail cache: path, size, modification time, inode.
pub type ThumbKey = (PathBuf, u64, i64, i64, u64);

pub struct Limits {
    streams: Arc<Semaphore>,
    decodes: Arc<Semaphore>,
    bodies: Arc<Semaphore>,
    thumbs: Mutex<ThumbCache>,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            streams: Arc::new(Semaphore::new(MAX_EVENT_STREAMS)),
            decodes: Arc::new(Semaphore::new(MAX_DECODES)),
            bodies: Arc::new(Semaphore::new(MAX_BODIES)),
            thumbs: Mutex::new(ThumbCache::default()),
        }
    }
}

impl Limits {
    /// A place for one more event stream, or `None` when they are all taken.
    pub fn stream(&self) -> Option<OwnedSemaphorePermit> {
        self.streams.clone().try_acquire_owned().ok()
    }

    /// A place for one more request body in memory, or `None` when they are all taken.
    pub fn body(&self) -> Option<OwnedSemaphorePermit> {
        self.bodies.clone().try_acquire_owned().ok()
    }

    /// Waits for a turn to decode an image.
    pub async fn decode(&self) -> OwnedSemaphorePermit {
        self.decodes.clone().acquire_owned().await.expect("never closed")
    }

    pub fn thumb(&self, key: &ThumbKey) -> Option<Bytes> {
        self.thumbs.lock().expect("thumbnail cache").get(key)
    }

    pub fn keep_thumb(&self, key: ThumbKey, jpeg: Bytes) {
        self.thumbs.lock().expect("thumbnail cache").put(key, jpeg);
    }
}

/// Thumbnails by file identity, bounded in bytes, oldest out first.
#[derive(Default)]
struct ThumbCache {
    entries: VecDeque<(ThumbKey, Bytes)>,
    bytes: usize,
}

impl ThumbCache {
    fn get(&self, key: &ThumbKey) -> Option<Bytes> {
        self.entries.iter().find(|(k, _)| k == key).map(|(_, v)| v.clone())
    }

    fn put(&mut self, key: ThumbKey, jpeg: Bytes) {
        if jpeg.len() > THUMB_CACHE_BYTES || self.get(&key).is_some() {
            return;
        }
        // An older version of the same file is of no use any more.
        self.entries.retain(|(k, v)| {
            let stale = k.0 == key.0;
            if stale {
                self.bytes -= v.len();
            }
            !stale
        });
        self.bytes += jpeg.len();
        self.entries.push_back((key, jpeg));
        while self.bytes > THUMB_CACHE_BYTES {
            let (_, v) = self.entries.pop_front().expect("bytes > 0 means entries");
            self.bytes -= v.len();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(name: &str, size: u64) -> ThumbKey {
        (PathBuf::from(name), size, 0, 0, 1)
    }

    #[test]
    fn the_thumbnail_cache_stays_within_its_bytes_and_forgets_old_versions() {
        let mut c = ThumbCache::default();
        let big = Bytes::from(vec![0u8; THUMB_CACHE_BYTES / 3]);
        for i in 0..5 {
            c.put(key(&format!("v{i}"), 1), big.clone());
        }
        assert!(c.bytes <= THUMB_CACHE_BYTES);
        assert_eq!(c.entries.len(), 3);
        assert!(c.get(&key("v4", 1)).is_some() && c.get(&key("v0", 1)).is_none());
        c.put(key("v4", 2), Bytes::from(vec![1u8; 10]));
        assert!(c.get(&key("v4", 1)).is_none(), "a new version replaces the old");
        assert_eq!(c.bytes, 2 * big.len() + 10);
    }

    #[test]
    fn streams_and_bodies_are_capped() {
        let l = Limits::default();
        let held: Vec<_> = (0..MAX_EVENT_STREAMS).map(|_| l.stream().unwrap()).collect();
        assert!(l.stream().is_none());
        drop(held);
        assert!(l.stream().is_some());
        let bodies: Vec<_> = (0..MAX_BODIES).map(|_| l.body().unwrap()).collect();
        assert!(l.body().is_none());
        drop(bodies);
    }
}
