//! The fill front's order: Criminisi's priority, confidence × data term, and a queue that
//! always hands out the most urgent front pixel (pure layer).
//!
//! Confidence says how much of a pixel's patch is already trustworthy; the data term how
//! strongly a linear structure (an isophote: a brick joint, a window frame) runs into the
//! hole at that point. Filling those first propagates structure before texture, so edges
//! continue across the hole instead of being grown over.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// Added to the data term so that flat regions still get filled (in confidence order).
pub const DATA_FLOOR: f32 = 1e-3;

/// Mean confidence of the known pixels of the `(2r+1)²` patch at `(x, y)` (the patch's
/// unknown pixels count as zero; pixels outside the image do not count).
pub fn confidence_term(
    conf: &[f32],
    known: &[bool],
    w: usize,
    h: usize,
    x: usize,
    y: usize,
    r: usize,
) -> f32 {
    let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
    let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
    let mut sum = 0.0;
    for yy in y0..y1 {
        let row = yy * w;
        for xx in x0..x1 {
            if known[row + xx] {
                sum += conf[row + xx];
            }
        }
    }
    sum / ((x1 - x0) * (y1 - y0)) as f32
}

/// The gradient of `gray` at a known pixel, from known neighbours only (central
/// differences where both are known, one-sided where one is).
fn known_gradient(gray: &[f32], known: &[bool], w: usize, h: usize, x: usize, y: usize) -> (f32, f32) {
    let i = y * w + x;
    let diff = |a: Option<usize>, b: Option<usize>| -> f32 {
        let a = a.filter(|&j| known[j]);
        let b = b.filter(|&j| known[j]);
        match (a, b) {
            (Some(a), Some(b)) => (gray[b] - gray[a]) * 0.5,
            (None, Some(b)) => gray[b] - gray[i],
            (Some(a), None) => gray[i] - gray[a],
            (None, None) => 0.0,
        }
    };
    let gx = diff((x > 0).then(|| i - 1), (x + 1 < w).then(|| i + 1));
    let gy = diff((y > 0).then(|| i - w), (y + 1 < h).then(|| i + w));
    (gx, gy)
}

/// Criminisi's data term `|∇I⊥ · n| + floor` at the front pixel `(x, y)`: `n` is the unit
/// normal of the front (from the known/unknown indicator), `∇I⊥` the strongest isophote
/// among the known pixels next to it.
pub fn data_term(gray: &[f32], known: &[bool], w: usize, h: usize, x: usize, y: usize) -> f32 {
    let k = |xx: isize, yy: isize| -> f32 {
        if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize {
            0.0
        } else if known[yy as usize * w + xx as usize] {
            1.0
        } else {
            0.0
        }
    };
    let (xi, yi) = (x as isize, y as isize);
    // Sobel of the indicator: points from the hole towards the known side.
    let nx = (k(xi + 1, yi - 1) + 2.0 * k(xi + 1, yi) + k(xi + 1, yi + 1))
        - (k(xi - 1, yi - 1) + 2.0 * k(xi - 1, yi) + k(xi - 1, yi + 1));
    let ny = (k(xi - 1, yi + 1) + 2.0 * k(xi, yi + 1) + k(xi + 1, yi + 1))
        - (k(xi - 1, yi - 1) + 2.0 * k(xi, yi - 1) + k(xi + 1, yi - 1));
    let norm = (nx * nx + ny * ny).sqrt();
    if norm < 1e-6 {
        return DATA_FLOOR;
    }
    let (nx, ny) = (nx / norm, ny / norm);
    let mut best = (0.0f32, 0.0f32, 0.0f32);
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            if known[yy * w + xx] {
                let (gx, gy) = known_gradient(gray, known, w, h, xx, yy);
                let m = gx * gx + gy * gy;
                if m > best.0 {
                    best = (m, gx, gy);
                }
            }
        }
    }
    // Isophote = gradient turned by 90°.
    let (ix, iy) = (-best.2, best.1);
    (ix * nx + iy * ny).abs() + DATA_FLOOR
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Entry {
    priority: f32,
    index: usize,
    stamp: u32,
}

impl Eq for Entry {}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        // Highest priority first; ties to the lower index (raster order), so the order is
        // fully determined by the image.
        self.priority.total_cmp(&other.priority).then_with(|| other.index.cmp(&self.index))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// Front pixels by priority. Re-pushing a pixel supersedes its earlier entry (stale
/// entries are skipped when popped), so updating a priority is one push.
#[derive(Debug, Clone)]
pub struct FrontQueue {
    heap: BinaryHeap<Entry>,
    stamp: Vec<u32>,
}

impl FrontQueue {
    /// A queue for pixel indices `0..n`.
    pub fn new(n: usize) -> Self {
        Self { heap: BinaryHeap::new(), stamp: vec![0; n] }
    }

    /// Sets (or replaces) the priority of pixel `index`.
    pub fn push(&mut self, index: usize, priority: f32) {
        self.stamp[index] = self.stamp[index].wrapping_add(1);
        self.heap.push(Entry { priority, index, stamp: self.stamp[index] });
    }

    /// Forgets pixel `index` (its entries become stale).
    pub fn remove(&mut self, index: usize) {
        self.stamp[index] = self.stamp[index].wrapping_add(1);
    }

    /// The most urgent pixel, removed from the queue.
    pub fn pop(&mut self) -> Option<usize> {
        while let Some(e) = self.heap.pop() {
            if self.stamp[e.index] == e.stamp {
                self.stamp[e.index] = self.stamp[e.index].wrapping_add(1);
                return Some(e.index);
            }
        }
        None
    }

    pub fn is_empty(&self) -> bool {
        self.heap.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn queue_orders_by_priority_and_replaces_entries() {
        let mut q = FrontQueue::new(10);
        q.push(3, 0.5);
        q.push(7, 0.9);
        q.push(1, 0.5);
        q.push(7, 0.1); // supersedes 0.9
        q.push(4, 0.2);
        q.remove(4);
        let order: Vec<_> = std::iter::from_fn(|| q.pop()).collect();
        assert_eq!(order, vec![1, 3, 7]);
    }

    /// A 20×20 image, left half dark, right half bright (a vertical edge at x = 10); the
    /// hole is the bottom half.
    fn edge_scene() -> (Vec<f32>, Vec<bool>, Vec<f32>) {
        let (w, h) = (20, 20);
        let gray: Vec<f32> = (0..w * h).map(|i| if i % w < 10 { 0.2 } else { 0.8 }).collect();
        let known: Vec<bool> = (0..w * h).map(|i| i / w < 10).collect();
        let conf: Vec<f32> = known.iter().map(|&k| if k { 1.0 } else { 0.0 }).collect();
        (gray, known, conf)
    }

    #[test]
    fn an_edge_running_into_the_hole_comes_first() {
        let (gray, known, conf) = edge_scene();
        let p = |x: usize| {
            confidence_term(&conf, &known, 20, 20, x, 10, 3) * data_term(&gray, &known, 20, 20, x, 10)
        };
        // On the front (row 10), where the edge meets it, versus flat stretches.
        assert!(p(10) > 10.0 * p(4), "edge {} flat {}", p(10), p(4));
        assert!(p(9) > 10.0 * p(15));
    }

    #[test]
    fn confidence_falls_with_depth_into_the_hole() {
        let (_, known, conf) = edge_scene();
        let c: Vec<f32> = (10..14).map(|y| confidence_term(&conf, &known, 20, 20, 5, y, 3)).collect();
        assert!(c.windows(2).all(|p| p[0] > p[1]), "{c:?}");
        assert!((c[0] - 3.0 / 7.0).abs() < 1e-6);
        assert_eq!(confidence_term(&conf, &known, 20, 20, 5, 14, 3), 0.0);
    }
}
