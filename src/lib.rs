//! umbra: relightable neural avatars from video. Bone-anchored anisotropic 3D Gaussians cast
//! shadows by a closed-form ray integral; a staged fit recovers light, ambient and albedo.

pub mod ablate;
pub mod averaging;
pub mod basis;
pub mod bench;
pub mod cli;
pub mod environment;
pub mod error_map;
pub mod eval;
pub mod export;
pub mod field;
pub mod fit;
pub mod fuzzing;
pub mod gaussians;
pub mod geometry;
pub mod imageio;
pub mod isosurface;
pub mod light;
pub mod losses;
pub mod metrics;
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
pub mod shading;
pub mod shadow;
pub mod skeleton;
pub mod sun_search;
pub mod synth;
pub mod train;
