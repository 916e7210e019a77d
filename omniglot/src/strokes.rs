//! Reader for the official Omniglot stroke files.
//!
//! Layout: `<root>/<Alphabet>/characterNN/NNNN_DD.txt`, where `<root>` is e.g. the official
//! `strokes_background/` or `strokes_evaluation/` folder unchanged, NNNN the global character
//! id and DD the drawer. A file is `START`, then one `x,y,t` line per point (motor
//! coordinates: x right, y up, the 105 x 105 image spans x in [0, 105], y in [-105, 0]; t in
//! ms), and `BREAK` after each stroke.

use std::path::{Path, PathBuf};

/// One pen sample in Omniglot motor coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    /// Motor x (right).
    pub x: f64,
    /// Motor y (up; the image spans [-105, 0]).
    pub y: f64,
    /// Time stamp (ms); not always monotonic in the data.
    pub t: f64,
}

/// One pen-down stroke: at least one point.
pub type Stroke = Vec<Point>;

/// A drawing file located in the Omniglot layout (not yet read).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct DrawingFile {
    /// Alphabet folder name, e.g. `Latin`.
    pub alphabet: String,
    /// Character folder name, e.g. `character01`.
    pub character: String,
    /// The drawer number DD from `NNNN_DD.txt`.
    pub drawer: u32,
    /// The global character id NNNN.
    pub character_id: u32,
    /// Where the file is.
    pub path: PathBuf,
}

impl DrawingFile {
    /// Class name `Alphabet/characterNN`.
    pub fn class_name(&self) -> String {
        format!("{}/{}", self.alphabet, self.character)
    }
}

/// Reading or locating stroke files failed. Every variant names the file (and line).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReadStrokesError {
    /// The file or folder could not be read.
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A point line before the first `START`.
    #[error("{}:{line}: missing START before {text:?}", path.display())]
    MissingStart {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The offending line.
        text: String,
    },
    /// A field is not a finite number.
    #[error("{}:{line}: bad number {field:?} in {text:?}", path.display())]
    BadNumber {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The field that failed.
        field: String,
        /// The whole line.
        text: String,
    },
    /// A line that is neither `START`, `BREAK` nor `x,y,t`.
    #[error("{}:{line}: expected START, BREAK or x,y,t, got {text:?}", path.display())]
    BadLine {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The offending line.
        text: String,
    },
    /// No point at all.
    #[error("{}: empty drawing (no points)", path.display())]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// A file name that is not `NNNN_DD.txt` inside a `characterNN` folder.
    #[error("{}: not an Omniglot stroke file name (<Alphabet>/characterNN/NNNN_DD.txt)", path.display())]
    FileName {
        /// The file.
        path: PathBuf,
    },
    /// The same alphabet appears under two roots.
    #[error("alphabet {alphabet} appears in both {} and {}", first.display(), second.display())]
    DuplicateAlphabet {
        /// The alphabet name.
        alphabet: String,
        /// First root.
        first: PathBuf,
        /// Second root.
        second: PathBuf,
    },
    /// The roots hold no drawing file at all.
    #[error("no stroke files under {roots:?}")]
    NoFiles {
        /// The roots searched.
        roots: Vec<PathBuf>,
    },
}

/// Parse the text of a stroke file; `path` is only used in errors. Empty strokes (`BREAK`
/// right after `START` or `BREAK`) are dropped; points after the last `BREAK` form a final
/// stroke.
pub fn parse_strokes(text: &str, path: &Path) -> Result<Vec<Stroke>, ReadStrokesError> {
    let mut strokes: Vec<Stroke> = Vec::new();
    let mut current: Stroke = Vec::new();
    let mut started = false;
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let trimmed = raw.trim();
        match trimmed {
            "" => continue,
            "START" => {
                started = true;
                continue;
            }
            "BREAK" => {
                if !started {
                    return Err(ReadStrokesError::MissingStart {
                        path: path.to_path_buf(),
                        line,
                        text: trimmed.to_string(),
                    });
                }
                if !current.is_empty() {
                    strokes.push(std::mem::take(&mut current));
                }
                continue;
            }
            _ => {}
        }
        if !started {
            return Err(ReadStrokesError::MissingStart {
                path: path.to_path_buf(),
                line,
                text: trimmed.to_string(),
            });
        }
        let fields: Vec<&str> = trimmed.split(',').map(str::trim).collect();
        if fields.len() != 3 {
            return Err(ReadStrokesError::BadLine {
                path: path.to_path_buf(),
                line,
                text: trimmed.to_string(),
            });
        }
        let mut v = [0.0f64; 3];
        for (slot, field) in v.iter_mut().zip(&fields) {
            *slot = match field.parse::<f64>() {
                Ok(x) if x.is_finite() => x,
                _ => {
                    return Err(ReadStrokesError::BadNumber {
                        path: path.to_path_buf(),
                        line,
                        field: (*field).to_string(),
                        text: trimmed.to_string(),
                    });
                }
            };
        }
        current.push(Point {
            x: v[0],
            y: v[1],
            t: v[2],
        });
    }
    if !current.is_empty() {
        strokes.push(current);
    }
    if strokes.is_empty() {
        return Err(ReadStrokesError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(strokes)
}

/// What is done to a drawing's strokes before it is converted: the two ways in which the
/// recovered alphabets (`../shared/omniglot/recovered`, README there) differ from the
/// official files, so that dense official drawings can be made to look like them and the
/// gap measured (`guardian-lab dataset --simplify --drop-dots`).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StrokePrep {
    /// Ramer-Douglas-Peucker tolerance in motor units (`None`: strokes as drawn).
    pub simplify: Option<f64>,
    /// Remove one-point strokes (dots), as the recovered files lack them. A drawing that is
    /// only dots keeps them (it would be empty otherwise).
    pub drop_dots: bool,
}

impl StrokePrep {
    /// Apply to one drawing's strokes.
    pub fn apply(&self, strokes: Vec<Stroke>) -> Vec<Stroke> {
        let mut out = strokes;
        if self.drop_dots && out.iter().any(|s| s.len() > 1) {
            out.retain(|s| s.len() > 1);
        }
        if let Some(eps) = self.simplify {
            out = out.iter().map(|s| simplify(s, eps)).collect();
        }
        out
    }
}

/// Ramer-Douglas-Peucker simplification of one stroke (x, y only; each kept point keeps its
/// time stamp): the fewest of its points such that no dropped point lies farther than `eps`
/// from the chord that replaces it. The first and last points are always kept.
pub fn simplify(stroke: &[Point], eps: f64) -> Stroke {
    if stroke.len() < 3 {
        return stroke.to_vec();
    }
    let mut keep = vec![false; stroke.len()];
    keep[0] = true;
    keep[stroke.len() - 1] = true;
    let mut todo = vec![(0, stroke.len() - 1)];
    while let Some((a, b)) = todo.pop() {
        let (pa, pb) = (stroke[a], stroke[b]);
        let (dx, dy) = (pb.x - pa.x, pb.y - pa.y);
        let len = dx.hypot(dy);
        let dist = |p: &Point| {
            if len > 0.0 {
                (dy * (p.x - pa.x) - dx * (p.y - pa.y)).abs() / len
            } else {
                (p.x - pa.x).hypot(p.y - pa.y)
            }
        };
        let far = (a + 1..b)
            .map(|i| (i, dist(&stroke[i])))
            .max_by(|x, y| x.1.total_cmp(&y.1));
        if let Some((i, d)) = far
            && d > eps
        {
            keep[i] = true;
            todo.push((a, i));
            todo.push((i, b));
        }
    }
    stroke
        .iter()
        .zip(keep)
        .filter_map(|(p, k)| k.then_some(*p))
        .collect()
}

/// Read and parse one stroke file.
pub fn read_strokes(path: &Path) -> Result<Vec<Stroke>, ReadStrokesError> {
    let text = std::fs::read_to_string(path).map_err(|source| ReadStrokesError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_strokes(&text, path)
}

/// Parse `NNNN_DD.txt` into (character id, drawer).
fn parse_file_name(name: &str) -> Option<(u32, u32)> {
    let stem = name.strip_suffix(".txt")?;
    let (id, drawer) = stem.split_once('_')?;
    let all_digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if !all_digits(id) || !all_digits(drawer) {
        return None;
    }
    Some((id.parse().ok()?, drawer.parse().ok()?))
}

fn sorted_entries(dir: &Path) -> Result<Vec<PathBuf>, ReadStrokesError> {
    let io = |source| ReadStrokesError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        out.push(entry.map_err(io)?.path());
    }
    out.sort();
    Ok(out)
}

/// The drawing files (`*.txt`) of `<root>/<alphabet>/characterNN`, sorted by name (that is,
/// by drawer).
pub fn character_files(
    root: &Path,
    alphabet: &str,
    character: u32,
) -> Result<Vec<PathBuf>, ReadStrokesError> {
    let dir = root.join(alphabet).join(format!("character{character:02}"));
    Ok(sorted_entries(&dir)?
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "txt"))
        .collect())
}

/// Find every drawing under the roots (each `<root>/<Alphabet>/characterNN/NNNN_DD.txt`),
/// sorted by alphabet, character, drawer. Hidden entries and files not ending in `.txt`
/// are ignored; a `.txt` file with a name other than `NNNN_DD.txt` is an error.
pub fn scan(roots: &[PathBuf]) -> Result<Vec<DrawingFile>, ReadStrokesError> {
    let mut files = Vec::new();
    let mut seen: std::collections::BTreeMap<String, PathBuf> = Default::default();
    for root in roots {
        for alphabet_dir in sorted_entries(root)? {
            let Some(alphabet) = visible_dir_name(&alphabet_dir) else {
                continue;
            };
            if let Some(first) = seen.insert(alphabet.clone(), root.clone()) {
                return Err(ReadStrokesError::DuplicateAlphabet {
                    alphabet,
                    first,
                    second: root.clone(),
                });
            }
            for character_dir in sorted_entries(&alphabet_dir)? {
                let Some(character) = visible_dir_name(&character_dir) else {
                    continue;
                };
                for file in sorted_entries(&character_dir)? {
                    let Some(name) = file.file_name().and_then(|n| n.to_str()) else {
                        continue;
                    };
                    if name.starts_with('.') || !name.ends_with(".txt") {
                        continue;
                    }
                    let Some((character_id, drawer)) = parse_file_name(name) else {
                        return Err(ReadStrokesError::FileName { path: file });
                    };
                    files.push(DrawingFile {
                        alphabet: alphabet.clone(),
                        character: character.clone(),
                        drawer,
                        character_id,
                        path: file,
                    });
                }
            }
        }
    }
    if files.is_empty() {
        return Err(ReadStrokesError::NoFiles {
            roots: roots.to_vec(),
        });
    }
    files.sort_by(|a, b| {
        (&a.alphabet, &a.character, a.drawer, &a.path).cmp(&(
            &b.alphabet,
            &b.character,
            b.drawer,
            &b.path,
        ))
    });
    Ok(files)
}

fn visible_dir_name(path: &Path) -> Option<String> {
    let name = path.file_name()?.to_str()?;
    (!name.starts_with('.') && path.is_dir()).then(|| name.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_points_and_breaks() {
        let text = "START\n1,-2,0\n3.5,-4,10\nBREAK\n5,-6,20\nBREAK\n";
        let s = parse_strokes(text, Path::new("x.txt")).expect("valid");
        assert_eq!(s.len(), 2);
        assert_eq!(s[0].len(), 2);
        assert_eq!(
            s[0][1],
            Point {
                x: 3.5,
                y: -4.0,
                t: 10.0
            }
        );
        assert_eq!(s[1].len(), 1);
    }

    #[test]
    fn simplification_keeps_corners_and_drops_straight_runs() {
        let p = |x: f64, y: f64| Point { x, y, t: 0.0 };
        // An L of 11 points: only its ends and its corner survive.
        let mut l: Stroke = (0..=5).map(|i| p(f64::from(i), 0.0)).collect();
        l.extend((1..=5).map(|i| p(5.0, f64::from(i))));
        let s = simplify(&l, 0.1);
        assert_eq!(s, vec![p(0.0, 0.0), p(5.0, 0.0), p(5.0, 5.0)]);
        // A bump of 0.5 is kept at eps 0.4 and dropped at eps 0.6.
        let bump = vec![
            p(0.0, 0.0),
            p(1.0, 0.0),
            p(2.0, 0.5),
            p(3.0, 0.0),
            p(4.0, 0.0),
        ];
        assert!(simplify(&bump, 0.4).contains(&p(2.0, 0.5)));
        assert_eq!(simplify(&bump, 0.6), vec![p(0.0, 0.0), p(4.0, 0.0)]);
        // A closed loop (first = last point) keeps its farthest point.
        let ring = vec![
            p(0.0, 0.0),
            p(2.0, 0.0),
            p(2.0, 2.0),
            p(0.0, 2.0),
            p(0.0, 0.0),
        ];
        assert!(simplify(&ring, 0.5).len() >= 3);
    }

    #[test]
    fn dots_are_dropped_unless_they_are_all_there_is() {
        let p = |x: f64| Point { x, y: 0.0, t: 0.0 };
        let prep = StrokePrep {
            simplify: None,
            drop_dots: true,
        };
        let drawing = vec![vec![p(0.0), p(1.0)], vec![p(5.0)], vec![p(2.0), p(3.0)]];
        assert_eq!(prep.apply(drawing).len(), 2);
        let only_dots = vec![vec![p(0.0)], vec![p(5.0)]];
        assert_eq!(prep.apply(only_dots.clone()), only_dots);
        assert_eq!(StrokePrep::default().apply(only_dots.clone()), only_dots);
    }

    #[test]
    fn file_names() {
        assert_eq!(parse_file_name("0683_01.txt"), Some((683, 1)));
        assert_eq!(parse_file_name("0683-01.txt"), None);
        assert_eq!(parse_file_name("0683_x1.txt"), None);
        assert_eq!(parse_file_name("0683_01.csv"), None);
    }
}
