//! Core types and maths of Content-Promoted Scene Layers (CPSL).
//!
//! Everything here is pure computation and (de)serialisation: cameras, poses, the
//! plane-induced homography of the paper (equation 1), premultiplied RGBA images, layers and
//! validated layer sets, the layer-set manifest schema and the [`Limits`] every reader obeys.
//!
//! # Conventions
//! * Camera coordinates follow OpenCV: `x` right, `y` down, `z` forward (into the scene).
//! * Pixel coordinates put **integer values at pixel centres**: pixel `(i, j)` covers
//!   `[i - 0.5, i + 0.5] x [j - 0.5, j + 0.5]`.
//! * A [`Pose`] is the viewer (target) camera expressed in the reference (source) camera frame:
//!   `X_ref = R * X_view + t`. See [`pose`] for the Euler-angle convention.
//! * Colours are stored premultiplied by alpha, 8 bits per channel.

pub mod camera;
pub mod context;
pub mod depth;
pub mod edc;
pub mod error;
pub mod fill;
pub mod frame;
pub mod geometry;
pub mod homography;
pub mod image;
pub mod layer;
pub mod limits;
pub mod manifest;
pub mod math;
pub mod motion;
pub mod pose;
pub mod progress;
pub mod resample;
pub mod run;
pub mod ycbcr;

pub use camera::Camera;
pub use depth::{median_depth, DepthSource, DepthSourceError, FixedDepth};
pub use edc::{Edc, EdcError, EdcSample};
pub use error::CoreError;
pub use frame::{LayeredFrame, RefreshReason};
pub use geometry::{fit_plane, DepthGrid, Geometry, GridError};
pub use homography::Homography;
pub use image::PremulImage;
pub use layer::{Layer, LayerMeta, LayerRole, LayerSet};
pub use limits::Limits;
pub use manifest::{
    check_head, CameraSpec, HeadError, LayerEntry, Manifest, ManifestError, FORMAT_NAME,
    FORMAT_VERSION,
};
pub use math::{Mat3, Vec3};
pub use motion::Flow;
pub use pose::Pose;
pub use progress::{NoProgress, Progress, ProgressEvent};
