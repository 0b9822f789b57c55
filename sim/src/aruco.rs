//! ArUco marker bits for drawing markers, from OpenCV's predefined dictionaries (carried here so
//! that the simulator, and robots that stream it, need no OpenCV).

#[rustfmt::skip]
mod bits;

/// A predefined dictionary the simulator can draw: `DICT_{4,5,6}X{4,5,6}_{50,100,250,1000}`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dictionary {
    /// Bits per side, without the black border.
    pub bits: usize,
    /// Number of markers.
    pub markers: usize,
}

impl Dictionary {
    /// Parses an OpenCV name such as `DICT_4X4_100` (case-insensitive).
    pub fn by_name(name: &str) -> Option<Self> {
        let upper = name.trim().to_ascii_uppercase();
        let rest = upper.strip_prefix("DICT_")?;
        let (grid, count) = rest.split_once('_')?;
        let bits = match grid {
            "4X4" => 4,
            "5X5" => 5,
            "6X6" => 6,
            _ => return None,
        };
        let markers = match count {
            "50" | "100" | "250" | "1000" => count.parse().ok()?,
            _ => return None,
        };
        Some(Self { bits, markers })
    }

    /// The marker `id`'s pattern, or `None` past the dictionary's end.
    pub fn marker(&self, id: u32) -> Option<MarkerBits> {
        let table: &[u64] = match self.bits {
            4 => &bits::DICT_4X4,
            5 => &bits::DICT_5X5,
            _ => &bits::DICT_6X6,
        };
        let id = id as usize;
        (id < self.markers).then(|| MarkerBits {
            bits: self.bits,
            code: table[id],
        })
    }
}

/// One marker's pattern.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MarkerBits {
    pub bits: usize,
    code: u64,
}

impl MarkerBits {
    /// Whether the cell at `row`, `col` (from the top left, counting the one-cell black border,
    /// so both in `0..bits + 2`) is white.
    pub fn white(&self, row: usize, col: usize) -> bool {
        let n = self.bits;
        if row == 0 || col == 0 || row > n || col > n {
            return false;
        }
        let index = (row - 1) * n + (col - 1);
        self.code >> (n * n - 1 - index) & 1 == 1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_unknown_ones_are_refused() {
        assert_eq!(
            Dictionary::by_name("dict_5x5_250"),
            Some(Dictionary {
                bits: 5,
                markers: 250
            })
        );
        for bad in [
            "DICT_7X7_50",
            "DICT_4X4_99",
            "4X4_50",
            "DICT_ARUCO_ORIGINAL",
        ] {
            assert_eq!(Dictionary::by_name(bad), None, "{bad}");
        }
        assert!(Dictionary::by_name("DICT_4X4_50")
            .unwrap()
            .marker(50)
            .is_none());
    }
}
