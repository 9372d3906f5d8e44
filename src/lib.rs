//! umbra: relightable neural avatars from video. Bone-anchored anisotropic 3D Gaussians cast
//! shadows by a closed-form ray integral; a staged fit recovers light, ambient and albedo.

// `!(x > 0.0)` is how a check here rejects NaN together with what is out of range; the lint's
// `partial_cmp` spelling hides that.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod ablate;
pub mod animate;
pub mod apng;
pub mod avatar;
pub mod averaging;
pub mod backend;
pub mod basis;
pub mod bench;
pub mod capture;
pub mod carve;
pub mod cli;
pub mod environment;
pub mod error_map;
pub mod eval;
pub mod export;
pub mod field;
pub mod files;
pub mod fit;
pub mod fit_error;
pub mod fit_report;
pub mod fuzzing;
pub mod gaussians;
pub mod geometry;
pub mod imageio;
pub mod isosurface;
pub mod light;
pub mod losses;
pub mod messages;
pub mod metrics;
pub mod photo;
pub mod plot;
pub mod progress;
pub mod random;
pub mod relight;
pub mod render;
pub mod report;
pub mod run;
pub mod run_lock;
pub mod scene;
pub mod schedule;
pub mod scoring;
pub mod seen;
pub mod shading;
pub mod shadow;
pub mod silhouette;
pub mod skeleton;
pub mod sun_search;
pub mod synth;
pub mod table;
pub mod threads;
pub mod train;
pub mod written;
