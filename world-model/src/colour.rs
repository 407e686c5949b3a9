//! Beacon colours: what the camera tells apart and what the tracking system tracks.

use serde::{Deserialize, Serialize};

/// Beacon colours the camera tells apart.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Colour {
    /// Red.
    Red,
    /// Green.
    Green,
    /// Blue.
    Blue,
    /// Yellow.
    Yellow,
    /// Magenta.
    Magenta,
    /// Cyan.
    Cyan,
}

impl Colour {
    /// All colours, in code order.
    pub const ALL: [Colour; 6] = [
        Colour::Red,
        Colour::Green,
        Colour::Blue,
        Colour::Yellow,
        Colour::Magenta,
        Colour::Cyan,
    ];

    /// A small code for shared memory.
    pub fn code(self) -> u8 {
        Self::ALL.iter().position(|c| *c == self).unwrap_or(0) as u8
    }

    /// Colour from its code.
    pub fn from_code(c: u8) -> Option<Colour> {
        Self::ALL.get(c as usize).copied()
    }

    /// The colour's name, lower case (as in scenario files).
    pub fn name(self) -> &'static str {
        match self {
            Colour::Red => "red",
            Colour::Green => "green",
            Colour::Blue => "blue",
            Colour::Yellow => "yellow",
            Colour::Magenta => "magenta",
            Colour::Cyan => "cyan",
        }
    }

    /// The colour called `name` (lower case).
    pub fn from_name(name: &str) -> Option<Colour> {
        Self::ALL.into_iter().find(|c| c.name() == name)
    }

    /// RGB for drawing.
    pub fn rgb(self) -> [u8; 3] {
        match self {
            Colour::Red => [220, 30, 30],
            Colour::Green => [30, 170, 30],
            Colour::Blue => [40, 60, 230],
            Colour::Yellow => [230, 200, 0],
            Colour::Magenta => [200, 0, 200],
            Colour::Cyan => [0, 190, 200],
        }
    }
}
