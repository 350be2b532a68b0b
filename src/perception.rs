//! What OFFIS perceives in one frame pair: the two-plane object (TPO) in view and the nearest
//! obstacle. This is the contract between perception (`offis`) and navigation (`pafsis`,
//! `mofis`), and what `flownav analyze` prints.

use serde::{Deserialize, Serialize};

/// The TPO classes, defined by geometry in DESIGN.md.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TpoShape {
    Wall,
    Corner,
    Door,
    Corridor,
    #[default]
    None,
}

impl TpoShape {
    pub const ALL: [TpoShape; 5] =
        [TpoShape::Wall, TpoShape::Corner, TpoShape::Door, TpoShape::Corridor, TpoShape::None];

    pub fn name(self) -> &'static str {
        match self {
            TpoShape::Wall => "wall",
            TpoShape::Corner => "corner",
            TpoShape::Door => "door",
            TpoShape::Corridor => "corridor",
            TpoShape::None => "none",
        }
    }
}

/// The recognised TPO.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Tpo {
    pub shape: TpoShape,
    /// Degree of the winning fine classifier output, in [0, 1].
    pub confidence: f64,
    /// Distance along the heading to the TPO's nearest plane, m; `None` when it cannot be
    /// estimated (robot not translating, no valid flow).
    pub distance_m: Option<f64>,
}

/// The nearest obstacle (anything that is not a TPO plane).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Obstacle {
    pub present: bool,
    pub distance_m: Option<f64>,
    /// Bearing in the robot frame, rad, positive to the left (REP-103).
    pub bearing_rad: Option<f64>,
    /// Cell `[row, col]` of the 8×8 layer-3 matrix that holds it (paper Fig. 6).
    pub cell: Option<[usize; 2]>,
}

/// One frame pair's perception.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Perception {
    pub tpo: Tpo,
    pub obstacle: Obstacle,
    /// Rough structure mask (paper §4.1, eq. 11), 4×4 of 0/1.
    pub rough: [[u8; 4]; 4],
    /// Fine structure mask (paper §4.2, eq. 12), 8×8 of 0/1.
    pub fine: [[u8; 8]; 8],
}
