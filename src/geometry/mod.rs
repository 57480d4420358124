//! Projective geometry of the plane: homographies and their robust estimation (pure layer).

pub mod homography;
pub mod planes;
pub mod robust;

pub use homography::{DltError, Homography, Rows, dlt};
pub use planes::{PlaneFit, PlaneParams, fit_planes};
pub use robust::{Correspondence, Estimate, Method, NoModel, RobustParams};
