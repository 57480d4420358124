//! Feature points and their correspondences between keyframe and view (pure layer).

pub mod descriptor;
pub mod harris;
pub mod matching;

pub use descriptor::{Descriptor, DescriptorParams, Keypoint};
pub use harris::{Corner, HarrisParams, harris};
pub use matching::{GuidedParams, Match, MatchParams, guided_match, match_descriptors};
