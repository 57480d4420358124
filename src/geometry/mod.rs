//! Projective geometry of the plane: homographies and their robust estimation (pure layer).

pub mod homography;
pub mod robust;

pub use homography::{DltError, Homography, Rows, dlt};
pub use robust::{Correspondence, Estimate, Method, NoModel, RobustParams};
