//! What a user states about a capture when importing it (`umbra import`'s flags): its length
//! unit, its up axis, the kind of light it was made under, where its files are and how large its
//! images may stay.

use std::path::PathBuf;

/// Reads `--max-size PIXELS`: a whole number of at least `SMALLEST_MAX_SIZE`.
pub fn parse_max_size(text: &str) -> Result<usize, String> {
    match text.trim().parse::<usize>() {
        Ok(n) if n >= SMALLEST_MAX_SIZE => Ok(n),
        _ => Err(format!(
            "{text:?}: images are kept at least {SMALLEST_MAX_SIZE} pixels on their longer side (a smaller image holds too little of the body to fit)"
        )),
    }
}

/// The smallest `--max-size`.
pub const SMALLEST_MAX_SIZE: usize = 16;

/// The capture's length unit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Units {
    M,
    Cm,
    Mm,
}

impl Units {
    pub fn metres(self) -> f64 {
        match self {
            Units::M => 1.0,
            Units::Cm => 0.01,
            Units::Mm => 0.001,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Units::M => "m",
            Units::Cm => "cm",
            Units::Mm => "mm",
        }
    }

    /// The unit that makes a body of `extent` (the diagonal of its joints' box, file units)
    /// nearest 1.5 m, a walking human's or a large dog's, in ratio.
    pub fn for_extent(extent: f64) -> Units {
        let off = |u: Units| ((extent * u.metres()) / 1.5).ln().abs();
        [Units::M, Units::Cm, Units::Mm].into_iter().min_by(|a, b| off(*a).total_cmp(&off(*b))).unwrap_or(Units::M)
    }
}

/// The capture's up axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Up {
    #[value(name = "+y")]
    PlusY,
    #[value(name = "+z")]
    PlusZ,
}

/// The light the capture was made under, unknown but of a kind.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum CaptureLight {
    Sun,
    Point,
    Uniform,
}

/// What `umbra import` is asked.
#[derive(Clone, Debug)]
pub struct ImportOptions {
    pub capture: PathBuf,
    pub out: PathBuf,
    pub light: CaptureLight,
    pub units: Option<Units>,
    pub up: Up,
    pub cameras: Option<PathBuf>,
    pub motion: Option<PathBuf>,
    pub masks: Option<PathBuf>,
    pub max_size: Option<usize>,
}
