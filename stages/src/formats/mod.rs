//! Reading and writing the files fure exchanges with the outside world.
//!
//! One module per format:
//!
//! | module      | files                                   | data                       |
//! |-------------|-----------------------------------------|----------------------------|
//! | [`json`]    | any serde type, pretty JSON             | `T: Serialize/Deserialize` |
//! | [`cameras`] | a views directory with `transforms*.json` (NeRF / instant-ngp / NeuS2), or a COLMAP one | [`CameraSet`](crate::data::camera::CameraSet) |
//! | [`colmap`]  | COLMAP sparse model `cameras`/`images` (`.txt`, `.bin`), with `images/` and `masks/` | [`CameraSet`](crate::data::camera::CameraSet) |
//! | [`images`]  | PNG (8/16 bit, gray/GA/RGB/RGBA), OpenEXR (float), JPEG (read only) | [`ImageF32`](crate::data::image::ImageF32) |
//! | [`obj`]     | Wavefront OBJ, one group per part       | [`Mesh`](crate::data::mesh::Mesh) |
//! | [`hair`]    | Cem Yuksel `.hair`                      | [`Strands`](crate::data::strands::Strands) |
//! | [`ply`]     | PLY polylines (vertex + edge elements)  | [`Strands`](crate::data::strands::Strands) |
//! | [`scalars`] | per-vertex floats, JSON `{"values": [...]}` | `Vec<f32>`             |
//! | [`blender`] | a groom as a Blender Python script (write only) | [`Strands`](crate::data::strands::Strands) + [`Mesh`](crate::data::mesh::Mesh) |
//! | [`usd`]     | a groom as USD `.usda`: BasisCurves + Mesh (write only) | [`Strands`](crate::data::strands::Strands) + [`Mesh`](crate::data::mesh::Mesh) |
//!
//! Common rules, kept by every module:
//!
//! - Readers never panic on bad input. Every failure is a [`FormatError`] that names the file, the
//!   position (`line:column` for text formats, a byte offset for binary ones, a JSON field path for
//!   JSON documents) and what was expected there.
//! - Writers create missing parent directories and write to `path` directly (the engine makes the
//!   publication atomic). They refuse non-finite numbers instead of writing them, and their output is
//!   a pure function of the data (same data, same bytes): no timestamps, no hash-map iteration order,
//!   no thread-count-dependent layout.
//! - Floats in text formats are written with Rust's `{}` formatting of `f32`, the shortest decimal
//!   that reads back to the same `f32`, so a write/read round trip is exact.
//!
//! Where the part labels of strands live: the PLY strand file carries them (a per-vertex `part`
//! property and a `comment fure parts [...]` header line with the names as a JSON array). The `.hair`
//! format keeps geometry, thickness and colour only: its 88-byte info field is too small for per-strand
//! labels, and a sidecar file would be an artifact the engine does not know about (a stage writes
//! only the paths of its output ports). Reading a `.hair` file therefore gives unlabelled strands.

use std::fmt;
use std::fs;
use std::io::{self, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use fure_stage_api::StageError;

pub mod blender;
pub mod cameras;
pub mod colmap;
pub mod hair;
pub mod images;
pub mod json;
pub mod obj;
pub mod ply;
pub mod scalars;
pub mod usd;

#[cfg(test)]
mod fuzz;

/// Where in a file a problem was found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Position {
    /// 1-based line and column of a text file.
    LineColumn { line: usize, column: usize },
    /// 1-based line of a text file.
    Line(usize),
    /// Byte offset from the start of a binary file.
    Byte(u64),
    /// A path inside a structured document, e.g. `frames[3].transform_matrix`.
    Field(String),
}

impl fmt::Display for Position {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Position::LineColumn { line, column } => write!(f, "line {line}, column {column}"),
            Position::Line(line) => write!(f, "line {line}"),
            Position::Byte(offset) => write!(f, "byte {offset}"),
            Position::Field(field) => write!(f, "field `{field}`"),
        }
    }
}

/// Everything that can go wrong reading or writing a file.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The operating system refused (missing file, permissions, full disk, ...).
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    /// The file's content is malformed at a known position.
    #[error("{}: {position}: {message}", path.display())]
    Malformed {
        path: PathBuf,
        position: Position,
        message: String,
    },
    /// The file (or the data to write) is unusable as a whole.
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
}

impl FormatError {
    pub fn io(path: &Path, source: io::Error) -> Self {
        FormatError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
    pub fn at(path: &Path, position: Position, message: impl fmt::Display) -> Self {
        FormatError::Malformed {
            path: path.to_path_buf(),
            position,
            message: message.to_string(),
        }
    }
    pub fn invalid(path: &Path, message: impl fmt::Display) -> Self {
        FormatError::Invalid {
            path: path.to_path_buf(),
            message: message.to_string(),
        }
    }
    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            FormatError::Io { path, .. }
            | FormatError::Malformed { path, .. }
            | FormatError::Invalid { path, .. } => path,
        }
    }
    /// The position inside the file, when known.
    pub fn position(&self) -> Option<&Position> {
        match self {
            FormatError::Malformed { position, .. } => Some(position),
            _ => None,
        }
    }
}

impl FormatError {
    /// The error as a stage input error on `port` (keeps the path; the message keeps the position).
    pub fn for_input(self, port: &str) -> StageError {
        match self {
            FormatError::Io { path, source } => StageError::Io { path, source },
            FormatError::Malformed {
                path,
                position,
                message,
            } => StageError::Input {
                port: port.to_string(),
                path,
                message: format!("{position}: {message}"),
            },
            FormatError::Invalid { path, message } => StageError::Input {
                port: port.to_string(),
                path,
                message,
            },
        }
    }
}

/// Reads strands by file extension: `.hair` ([`hair::read_hair`]) or `.ply`
/// ([`ply::read_ply_strands`]).
pub fn read_strands(path: impl AsRef<Path>) -> Result<crate::data::strands::Strands, FormatError> {
    let path = path.as_ref();
    match extension(path).as_str() {
        "hair" => hair::read_hair(path),
        "ply" => ply::read_ply_strands(path),
        other => Err(FormatError::invalid(
            path,
            format!("unsupported strand file extension `{other}`: expected .hair or .ply"),
        )),
    }
}

/// Writes strands by file extension: `.hair` or `.ply` (binary little endian).
pub fn write_strands(
    path: impl AsRef<Path>,
    strands: &crate::data::strands::Strands,
) -> Result<(), FormatError> {
    let path = path.as_ref();
    match extension(path).as_str() {
        "hair" => hair::write_hair(path, strands),
        "ply" => ply::write_ply_strands(path, strands),
        other => Err(FormatError::invalid(
            path,
            format!("unsupported strand file extension `{other}`: expected .hair or .ply"),
        )),
    }
}

/// Lower-case extension of a path ("" when none).
pub(crate) fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}

impl From<FormatError> for StageError {
    fn from(e: FormatError) -> Self {
        match e {
            FormatError::Io { path, source } => StageError::Io { path, source },
            other => StageError::Failed(other.to_string()),
        }
    }
}

/// Reads a whole file, mapping the error to [`FormatError::Io`].
pub(crate) fn read_bytes(path: &Path) -> Result<Vec<u8>, FormatError> {
    fs::read(path).map_err(|e| FormatError::io(path, e))
}

/// Writes a whole file, creating parent directories first.
pub(crate) fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), FormatError> {
    create_parent(path)?;
    fs::write(path, bytes).map_err(|e| FormatError::io(path, e))
}

/// Creates the parent directory of `path` if it is missing.
pub(crate) fn create_parent(path: &Path) -> Result<(), FormatError> {
    if let Some(parent) = path.parent() {
        if !parent.as_os_str().is_empty() {
            fs::create_dir_all(parent).map_err(|e| FormatError::io(parent, e))?;
        }
    }
    Ok(())
}

/// A reader over an in-memory file that remembers the furthest byte a decoder asked for, so that a
/// decoder's error (which rarely carries a position) can be reported at the byte where it stopped.
pub(crate) struct TrackingReader<'a> {
    inner: io::Cursor<&'a [u8]>,
    furthest: u64,
}

impl<'a> TrackingReader<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        TrackingReader {
            inner: io::Cursor::new(bytes),
            furthest: 0,
        }
    }
    /// The furthest byte offset read so far.
    pub(crate) fn furthest(&self) -> u64 {
        self.furthest
    }
}

impl Read for TrackingReader<'_> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.furthest = self.furthest.max(self.inner.position());
        Ok(n)
    }
}

impl io::BufRead for TrackingReader<'_> {
    fn fill_buf(&mut self) -> io::Result<&[u8]> {
        self.inner.fill_buf()
    }
    fn consume(&mut self, amt: usize) {
        self.inner.consume(amt);
        self.furthest = self.furthest.max(self.inner.position());
    }
}

impl Seek for TrackingReader<'_> {
    fn seek(&mut self, pos: SeekFrom) -> io::Result<u64> {
        self.inner.seek(pos)
    }
}

/// Checks that every value is finite before writing, naming the first offender.
pub(crate) fn check_finite<I: IntoIterator<Item = f32>>(
    path: &Path,
    what: &str,
    values: I,
) -> Result<(), FormatError> {
    for (i, v) in values.into_iter().enumerate() {
        if !v.is_finite() {
            return Err(FormatError::invalid(
                path,
                format!("refusing to write non-finite value {v} at {what} index {i}"),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strands_dispatch_by_extension_and_errors_convert() {
        let dir = tempfile::tempdir().unwrap();
        let s = hair::tests::sample();
        for name in ["a.hair", "a.PLY"] {
            let p = dir.path().join(name);
            write_strands(&p, &s).unwrap();
            let back = read_strands(&p).unwrap();
            assert_eq!(back.points, s.points);
            assert_eq!(back.width, s.width);
        }
        let e = read_strands(dir.path().join("a.abc")).unwrap_err();
        assert!(e.to_string().contains("a.abc"));
        std::fs::write(dir.path().join("b.ply"), "ply\nformat ascii 2.0\n").unwrap();
        let e = read_strands(dir.path().join("b.ply")).unwrap_err();
        let msg = e.to_string();
        match e.for_input("strands") {
            StageError::Input {
                port,
                path,
                message,
            } => {
                assert_eq!(port, "strands");
                assert!(path.ends_with("b.ply"));
                assert!(message.contains("line 2"), "{message}");
                assert!(msg.contains(&message), "{msg} / {message}");
            }
            other => panic!("{other}"),
        }
    }
}
