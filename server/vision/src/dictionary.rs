//! ArUco dictionaries: OpenCV's predefined ones by name, or a custom one from OpenCV's
//! FileStorage YAML (`nmarkers`, `markersize`, optional `maxCorrectionBits`, `marker_N` bit
//! strings, row-major, 1 = white), as written by `cv::aruco::Dictionary::writeDictionary`.

use crate::image::GreyImage;
use crate::CvError;
use opencv::aruco::Dictionary;
use opencv::core::{Mat, Ptr};
use opencv::prelude::*;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// OpenCV's predefined dictionaries, by the names of its `PREDEFINED_DICTIONARY_NAME` enum.
pub const PREDEFINED: [&str; 21] = [
    "DICT_4X4_50",
    "DICT_4X4_100",
    "DICT_4X4_250",
    "DICT_4X4_1000",
    "DICT_5X5_50",
    "DICT_5X5_100",
    "DICT_5X5_250",
    "DICT_5X5_1000",
    "DICT_6X6_50",
    "DICT_6X6_100",
    "DICT_6X6_250",
    "DICT_6X6_1000",
    "DICT_7X7_50",
    "DICT_7X7_100",
    "DICT_7X7_250",
    "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
    "DICT_APRILTAG_16h5",
    "DICT_APRILTAG_25h9",
    "DICT_APRILTAG_36h10",
    "DICT_APRILTAG_36h11",
];

#[derive(Debug, Error)]
pub enum DictionaryError {
    #[error("unknown dictionary {0:?}; OpenCV's predefined ones are {list}", list = PREDEFINED.join(", "))]
    UnknownName(String),
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {message}")]
    Parse {
        path: PathBuf,
        line: usize,
        message: String,
    },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error(transparent)]
    Cv(#[from] CvError),
}

/// A dictionary and where it came from. Plain data, so it can be cloned and sent to worker
/// threads; each builds its own OpenCV object with [`MarkerDictionary::opencv`].
#[derive(Clone, PartialEq, Eq)]
pub struct MarkerDictionary {
    pub name: String,
    pub marker_size: i32,
    pub markers: i32,
    source: Source,
}

#[derive(Clone, PartialEq, Eq)]
enum Source {
    Predefined(i32),
    /// Bit codes (row-major, 1 = white) and the bits the decoder may correct.
    Custom {
        codes: Vec<Vec<u8>>,
        max_correction: i32,
    },
}

impl std::fmt::Debug for MarkerDictionary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({} markers of {}x{} bits)",
            self.name, self.markers, self.marker_size, self.marker_size
        )
    }
}

/// The index in [`PREDEFINED`] of the dictionary `name` names.
fn predefined_index(name: &str) -> Option<usize> {
    let wanted = name.trim().to_ascii_uppercase();
    let wanted = if wanted.starts_with("DICT_") {
        wanted
    } else {
        format!("DICT_{wanted}")
    };
    PREDEFINED
        .iter()
        .position(|n| n.to_ascii_uppercase() == wanted)
}

impl MarkerDictionary {
    /// Whether `name` names a predefined dictionary, as [`MarkerDictionary::predefined`] reads it.
    pub fn is_predefined(name: &str) -> bool {
        predefined_index(name).is_some()
    }

    /// A predefined dictionary, e.g. "DICT_6X6_250" (case-insensitive; "DICT_" may be left out).
    pub fn predefined(name: &str) -> Result<Self, DictionaryError> {
        let index =
            predefined_index(name).ok_or_else(|| DictionaryError::UnknownName(name.to_owned()))?;
        let source = Source::Predefined(index as i32);
        let inner = opencv::aruco::get_predefined_dictionary_i32(index as i32).map_err(CvError)?;
        Ok(Self {
            name: PREDEFINED[index].to_owned(),
            marker_size: inner.marker_size(),
            markers: inner.bytes_list().rows(),
            source,
        })
    }

    /// The OpenCV dictionary object.
    pub(crate) fn opencv(&self) -> Result<Ptr<Dictionary>, CvError> {
        match &self.source {
            Source::Predefined(index) => Ok(opencv::aruco::get_predefined_dictionary_i32(*index)?),
            Source::Custom {
                codes,
                max_correction,
            } => {
                let size = self.marker_size;
                let mut bytes_list = Mat::default();
                for code in codes {
                    let bits = Mat::new_rows_cols_with_data(size, size, code.as_slice())?;
                    bytes_list.push_back(&Dictionary::get_byte_list_from_bits(&bits)?)?;
                }
                Ok(Ptr::new(Dictionary::new(
                    &bytes_list,
                    size,
                    *max_correction,
                )?))
            }
        }
    }

    /// Reads a custom dictionary from an OpenCV FileStorage YAML file.
    pub fn from_yaml_file(path: &Path) -> Result<Self, DictionaryError> {
        let text = std::fs::read_to_string(path).map_err(|source| DictionaryError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_yaml(&text, path)
    }

    /// Parses the YAML text of a custom dictionary; `path` names it in errors.
    pub fn from_yaml(text: &str, path: &Path) -> Result<Self, DictionaryError> {
        let mut markers: Option<usize> = None;
        let mut size: Option<usize> = None;
        let mut max_correction: Option<i32> = None;
        let mut bits: Vec<Option<String>> = Vec::new();
        for (index, line) in text.lines().enumerate() {
            let parse = |message: String| DictionaryError::Parse {
                path: path.to_owned(),
                line: index + 1,
                message,
            };
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() || line.starts_with('%') || line == "---" {
                continue;
            }
            let Some((key, value)) = line.split_once(':') else {
                return Err(parse(format!("expected `key: value`, found {line:?}")));
            };
            let (key, value) = (key.trim(), value.trim().trim_matches('"'));
            let number = |v: &str| {
                v.parse::<usize>()
                    .map_err(|_| parse(format!("{key}: {v:?} is not a whole number")))
            };
            match key {
                "nmarkers" => markers = Some(number(value)?),
                "markersize" => size = Some(number(value)?),
                "maxCorrectionBits" => max_correction = Some(number(value)? as i32),
                _ => {
                    let Some(id) = key.strip_prefix("marker_") else {
                        return Err(parse(format!("unknown key {key:?}")));
                    };
                    let id = number(id)?;
                    if id >= 100_000 {
                        return Err(parse(format!("marker id {id} is too large")));
                    }
                    if bits.len() <= id {
                        bits.resize(id + 1, None);
                    }
                    if bits[id].replace(value.to_owned()).is_some() {
                        return Err(parse(format!("marker_{id} is given twice")));
                    }
                }
            }
        }
        let invalid = |message: String| DictionaryError::Invalid {
            path: path.to_owned(),
            message,
        };
        let size = size.ok_or_else(|| invalid("markersize is missing".into()))?;
        if !(2..=16).contains(&size) {
            return Err(invalid(format!("markersize {size} is outside 2..=16")));
        }
        let count = markers.unwrap_or(bits.len());
        if count == 0 || bits.len() != count || bits.iter().any(Option::is_none) {
            return Err(invalid(format!(
                "nmarkers is {count} but marker_0..marker_{} are not all given exactly",
                count.saturating_sub(1)
            )));
        }
        let codes: Vec<Vec<u8>> = bits
            .into_iter()
            .enumerate()
            .map(|(id, b)| {
                let b = b.expect("checked above");
                if b.len() != size * size || !b.bytes().all(|c| c == b'0' || c == b'1') {
                    return Err(invalid(format!(
                        "marker_{id} needs {} bits of 0 and 1, found {b:?}",
                        size * size
                    )));
                }
                Ok(b.bytes().map(|c| c - b'0').collect())
            })
            .collect::<Result<_, _>>()?;
        let max_correction =
            max_correction.unwrap_or_else(|| (min_distance(&codes, size) as i32 - 1).max(0) / 2);
        let name = path
            .file_name()
            .map_or_else(|| "custom".into(), |n| n.to_string_lossy().into_owned());
        let dictionary = Self {
            name,
            marker_size: size as i32,
            markers: codes.len() as i32,
            source: Source::Custom {
                codes,
                max_correction,
            },
        };
        dictionary.opencv()?;
        Ok(dictionary)
    }

    /// The marker's image with a one-bit black border, `side_px` pixels square (white = 255).
    pub fn draw(&self, id: i32, side_px: i32) -> Result<GreyImage, CvError> {
        let mut image = Mat::default();
        opencv::aruco::draw_marker(&self.opencv()?, id, side_px, &mut image, 1)?;
        GreyImage::from_mat(image)
    }
}

/// Smallest Hamming distance between two markers, or a marker and a rotation of itself or another.
fn min_distance(codes: &[Vec<u8>], size: usize) -> usize {
    let rotate = |code: &[u8]| -> Vec<u8> {
        let mut out = vec![0; code.len()];
        for y in 0..size {
            for x in 0..size {
                out[x * size + (size - 1 - y)] = code[y * size + x];
            }
        }
        out
    };
    let distance = |a: &[u8], b: &[u8]| a.iter().zip(b).filter(|(x, y)| x != y).count();
    let mut best = usize::MAX;
    for (i, a) in codes.iter().enumerate() {
        let mut rotated = a.clone();
        for turn in 0..4 {
            if turn > 0 {
                best = best.min(distance(a, &rotated));
            }
            for b in &codes[i + 1..] {
                best = best.min(distance(&rotated, b));
            }
            rotated = rotate(&rotated);
        }
    }
    if best == usize::MAX {
        size * size
    } else {
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn predefined_names_are_forgiving_and_checked() {
        assert_eq!(
            MarkerDictionary::predefined("DICT_6X6_250")
                .unwrap()
                .markers,
            250
        );
        let d = MarkerDictionary::predefined("4x4_50").unwrap();
        assert_eq!((d.name.as_str(), d.marker_size), ("DICT_4X4_50", 4));
        assert_eq!(
            MarkerDictionary::predefined("apriltag_36h11")
                .unwrap()
                .marker_size,
            6
        );
        let error = MarkerDictionary::predefined("DICT_9X9")
            .unwrap_err()
            .to_string();
        assert!(error.contains("DICT_5X5_100"), "{error}");
    }

    #[test]
    fn broken_yaml_is_explained() {
        let path = Path::new("d.yml");
        let err = |t: &str| {
            MarkerDictionary::from_yaml(t, path)
                .unwrap_err()
                .to_string()
        };
        assert!(err("nmarkers: 1\nmarkersize: 2\nmarker_0: \"101\"\n").contains("needs 4 bits"));
        assert!(err("nmarkers: 2\nmarkersize: 2\nmarker_0: \"1010\"\n").contains("nmarkers is 2"));
        assert!(err("nmarkers: x\n").contains(":1:"));
        assert!(err("markersize: 2\nmarker_0: \"1010\"\nmarker_0: \"1010\"\n").contains("twice"));
        assert!(err("nmarkers: 1\nmarker_0: \"1010\"\n").contains("markersize is missing"));
    }

    #[test]
    fn rotation_distance_counts_self_symmetry() {
        // A 2x2 code with one white bit turns into itself shifted: distance 2 to its rotations.
        assert_eq!(min_distance(&[vec![1, 0, 0, 0]], 2), 2);
        assert_eq!(min_distance(&[vec![1, 0, 0, 0], vec![0, 0, 0, 1]], 2), 0);
    }
}
