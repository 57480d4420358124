//! Which frame of a video becomes the keyframe (pure policy, tested without a stream).

use std::collections::VecDeque;

use crate::config::VideoKeyframe;

/// Which frame becomes the keyframe, judged with a look at the frames around it (pure
/// policy, tested without a stream).
///
/// The frame the user names (`keyframe_frame` N, or the first frame at or after
/// `keyframe_at_s`) is the keyframe, exactly: the mask was painted on it. It is judged
/// sharp against its neighbours (up to `window` frames before and after it): blurred when
/// its sharpness ([`crate::imaging::sharpness::sharpness`]) is below `min_sharpness` times
/// theirs at best. A blurred named frame is refused with a reason, never replaced by
/// another. Without a name, the keyframe is the first frame unless it is blurred, then the
/// next sharp one.
#[derive(Debug, Clone)]
pub(super) struct KeyPick {
    rule: VideoKeyframe,
    min_sharpness: f32,
    window: usize,
    /// Sharpness of the last `window` frames read.
    recent: VecDeque<f32>,
    pending: Option<PendingKey>,
    pub(super) done: bool,
}

/// A candidate keyframe waiting for its neighbours after it.
#[derive(Debug, Clone)]
struct PendingKey {
    index: u64,
    t: f64,
    rgb: Vec<u8>,
    sharpness: f32,
    /// The sharpest neighbour so far.
    best_neighbour: f32,
    after: usize,
}

/// What the chooser made of a frame.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum KeyStep {
    /// Nothing decided (the frame is an ordinary one).
    Wait,
    /// The frame at `index` is the keyframe.
    Key { index: u64, t: f64, rgb: Vec<u8> },
    /// The named frame is blurred: the session cannot start.
    Refused { reason: String },
}

impl KeyPick {
    pub(super) fn new(rule: VideoKeyframe, min_sharpness: f32, window: usize) -> Self {
        Self { rule, min_sharpness, window, recent: VecDeque::new(), pending: None, done: false }
    }

    /// Whether the keyframe is decided (accepted; a refusal ends the stream).
    pub(super) fn decided(&self) -> bool {
        self.done
    }

    /// Whether a frame is waiting to be judged as the keyframe.
    pub(super) fn pending(&self) -> bool {
        self.pending.is_some()
    }

    pub(super) fn is_candidate(&self, index: u64, t: f64) -> bool {
        !self.done
            && self.pending.is_none()
            && match self.rule {
                VideoKeyframe::First => true,
                VideoKeyframe::AtFrame(n) => index == n,
                VideoKeyframe::AtSeconds(at) => t + 1e-9 >= at,
            }
    }

    /// Offers the frame at `index` (its pixels and sharpness).
    pub(super) fn offer(&mut self, index: u64, t: f64, rgb: &[u8], sharpness: f32) -> KeyStep {
        if self.done {
            return KeyStep::Wait;
        }
        let mut step = KeyStep::Wait;
        if let Some(p) = &mut self.pending {
            p.best_neighbour = p.best_neighbour.max(sharpness);
            p.after += 1;
            if p.after >= self.window {
                step = self.judge();
            }
        } else if self.is_candidate(index, t) {
            let best_before = self.recent.iter().copied().fold(0.0f32, f32::max);
            self.pending = Some(PendingKey {
                index,
                t,
                rgb: rgb.to_vec(),
                sharpness,
                best_neighbour: best_before,
                after: 0,
            });
            if self.window == 0 {
                step = self.judge();
            }
        }
        if self.recent.len() == self.window.max(1) {
            self.recent.pop_front();
        }
        self.recent.push_back(sharpness);
        step
    }

    /// Why a stream that ended after `frames` frames (the last at `last_t` seconds) gave no
    /// keyframe: the frame it names is past its end, or none of its frames was sharp;
    /// `None` when the keyframe was chosen or one is waiting to be judged.
    pub(super) fn missed(&self, frames: u64, last_t: f64) -> Option<String> {
        if self.done || self.pending.is_some() {
            return None;
        }
        Some(match self.rule {
            VideoKeyframe::AtFrame(n) => format!(
                "frame {n} (keyframe_frame) is past the end of the video: its frames are 0 to {}",
                frames.saturating_sub(1)
            ),
            VideoKeyframe::AtSeconds(at) => format!(
                "{at} s (keyframe_at_s) is past the end of the video: its last frame is at {last_t:.3} s"
            ),
            VideoKeyframe::First => format!("none of its {frames} frames is sharp enough to be the keyframe"),
        })
    }

    /// The stream ended: judge a waiting candidate on the neighbours it had.
    pub(super) fn finish(&mut self) -> KeyStep {
        if self.pending.is_some() { self.judge() } else { KeyStep::Wait }
    }

    fn judge(&mut self) -> KeyStep {
        let p = self.pending.take().expect("a pending keyframe");
        let share = if p.best_neighbour > 0.0 { p.sharpness / p.best_neighbour } else { 1.0 };
        if share >= self.min_sharpness {
            self.done = true;
            return KeyStep::Key { index: p.index, t: p.t, rgb: p.rgb };
        }
        let named = match self.rule {
            VideoKeyframe::First => None,
            VideoKeyframe::AtFrame(n) => Some(format!("frame {n} (keyframe_frame)")),
            VideoKeyframe::AtSeconds(at) => {
                Some(format!("frame {} at {:.3} s (keyframe_at_s = {at})", p.index, p.t))
            }
        };
        match named {
            Some(which) => {
                self.done = true;
                KeyStep::Refused {
                    reason: format!(
                        "{which} is blurred ({:.0} % of the sharpness of the frames around it, {:.0} % needed): \
                         name a sharp frame and paint the mask on that one",
                        100.0 * share,
                        100.0 * self.min_sharpness
                    ),
                }
            }
            // The first frame was blurred: the next frame is the next candidate.
            None => KeyStep::Wait,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Feeds sharpness values to a chooser; the frame's pixels are its index.
    fn pick_over(rule: VideoKeyframe, sharpness: &[f32]) -> Vec<(u64, KeyStep)> {
        let mut pick = KeyPick::new(rule, 0.5, 3);
        let mut out = Vec::new();
        for (i, &s) in sharpness.iter().enumerate() {
            let step = pick.offer(i as u64, i as f64 / 10.0, &[i as u8], s);
            if step != KeyStep::Wait {
                out.push((i as u64, step));
            }
        }
        let step = pick.finish();
        if step != KeyStep::Wait {
            out.push((sharpness.len() as u64, step));
        }
        out
    }

    fn key_index(steps: &[(u64, KeyStep)]) -> Option<u64> {
        steps.iter().find_map(|(_, s)| match s {
            KeyStep::Key { index, .. } => Some(*index),
            _ => None,
        })
    }

    #[test]
    fn a_stream_that_ends_before_its_keyframe_says_why() {
        let ended = |rule: VideoKeyframe, sharpness: &[f32]| {
            let mut pick = KeyPick::new(rule, 0.5, 3);
            for (i, &s) in sharpness.iter().enumerate() {
                pick.offer(i as u64, i as f64 / 10.0, &[i as u8], s);
            }
            pick.finish();
            pick.missed(sharpness.len() as u64, (sharpness.len() - 1) as f64 / 10.0)
        };
        let sharp = [1.0; 8];
        assert_eq!(
            ended(VideoKeyframe::AtFrame(8), &sharp).as_deref(),
            Some("frame 8 (keyframe_frame) is past the end of the video: its frames are 0 to 7")
        );
        assert_eq!(
            ended(VideoKeyframe::AtSeconds(0.75), &sharp).as_deref(),
            Some("0.75 s (keyframe_at_s) is past the end of the video: its last frame is at 0.700 s")
        );
        // Reached, even as the last frame (judged on the neighbours it had): nothing missed.
        assert_eq!(ended(VideoKeyframe::AtFrame(7), &sharp), None);
        assert_eq!(ended(VideoKeyframe::AtSeconds(0.7), &sharp), None);
        assert_eq!(ended(VideoKeyframe::First, &sharp), None);
    }

    #[test]
    fn the_named_frame_is_the_keyframe_exactly_even_at_the_start() {
        let sharp = [10.0; 40];
        // Frame 0 without a name, frame 0 and frame 30 by number, 30 by time: exactly those.
        assert_eq!(key_index(&pick_over(VideoKeyframe::First, &sharp)), Some(0));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(0), &sharp)), Some(0));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(30), &sharp)), Some(30));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtSeconds(3.0), &sharp)), Some(30));
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtSeconds(2.95), &sharp)), Some(30));
        // The last frame is judged on the neighbours it has when the stream ends.
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(39), &sharp)), Some(39));
        // A frame past the end is never the keyframe.
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(40), &sharp)), None);
    }

    #[test]
    fn a_blurred_named_frame_is_refused_and_a_blurred_first_frame_skipped() {
        let mut s = [10.0f32; 40];
        s[0] = 2.0;
        s[30] = 3.0;
        let steps = pick_over(VideoKeyframe::AtFrame(30), &s);
        assert!(
            matches!(&steps[..], [(_, KeyStep::Refused { reason })] if reason.contains("frame 30") && reason.contains("blurred")),
            "{steps:?}"
        );
        assert!(matches!(&pick_over(VideoKeyframe::AtSeconds(3.0), &s)[..], [(_, KeyStep::Refused { .. })]));
        // Without a name the blurred first frame gives way to the next sharp one.
        let first = key_index(&pick_over(VideoKeyframe::First, &s)).unwrap();
        assert!(first > 0 && first < 10, "{first}");
        // Sharp enough against its neighbours (a uniformly soft video): accepted.
        assert_eq!(key_index(&pick_over(VideoKeyframe::AtFrame(5), &[2.0; 10])), Some(5));
    }
}
