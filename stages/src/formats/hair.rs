//! Cem Yuksel's `.hair` strand format (cemyuksel.com/research/hairmodels).
//!
//! Layout, all little endian: a 128-byte header
//!
//! | bytes    | field                                                                    |
//! |----------|--------------------------------------------------------------------------|
//! | 0..4     | `"HAIR"`                                                                 |
//! | 4..8     | hair count (u32)                                                         |
//! | 8..12    | point count (u32)                                                        |
//! | 12..16   | flags: 1 segments, 2 points, 4 thickness, 8 transparency, 16 colours      |
//! | 16..20   | default segment count (u32), used when there is no segments array        |
//! | 20..24   | default thickness (f32)                                                  |
//! | 24..28   | default transparency (f32)                                               |
//! | 28..40   | default colour (3 x f32)                                                 |
//! | 40..128  | info: 88 bytes of free text, NUL padded                                  |
//!
//! then the arrays whose flag is set, in this order: segments `u16[hair count]` (segments per hair,
//! points = segments + 1), points `f32[3 x point count]`, thickness `f32[point count]`,
//! transparency `f32[point count]`, colours `f32[3 x point count]`.
//!
//! Mapping to [`Strands`]: the format stores thickness and colour per point; ours are per strand.
//! Writing repeats the strand's value at every point, with the defaults set to the first strand's
//! values, and leaves out the segments, thickness or colour array when every strand has the same
//! value (the default then holds it: strands of one length, or the untextured snapshots of the
//! learners, are about half the size); reading takes the value at a strand's root point, so our
//! own files round-trip exactly. Transparency is read
//! past and ignored. A file without a thickness array gets the header's default thickness for
//! every strand, likewise for colours. `.hair` has no place for part labels (the info field is 88
//! bytes for the whole file): read strands are unlabelled (part 0, no part names); the PLY format
//! keeps labels (see [`super::ply`]). Writing fails for a strand of more than 65536 points (the
//! segment count is a u16) and for a file with more than 2^32 - 1 points.

use std::path::Path;

use glam::Vec3;

use super::{check_finite, read_bytes, write_bytes, FormatError, Position};
use crate::data::strands::Strands;

const HEADER: usize = 128;
const FLAG_SEGMENTS: u32 = 1;
const FLAG_POINTS: u32 = 2;
const FLAG_THICKNESS: u32 = 4;
const FLAG_TRANSPARENCY: u32 = 8;
const FLAG_COLORS: u32 = 16;
const INFO: &str = "fure strands (per-strand thickness and colour; part labels are in the PLY)";

/// Reads a `.hair` file.
pub fn read_hair(path: impl AsRef<Path>) -> Result<Strands, FormatError> {
    let path = path.as_ref();
    let bytes = read_bytes(path)?;
    parse(path, &bytes)
}

struct Cursor<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    /// Takes `n` bytes, or fails naming the array being read.
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], FormatError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        match end {
            Some(end) => {
                let s = &self.bytes[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(FormatError::at(
                self.path,
                Position::Byte(self.bytes.len() as u64),
                format!(
                    "file ends inside the {what} (expected {n} bytes from byte {}, file has {})",
                    self.pos,
                    self.bytes.len()
                ),
            )),
        }
    }
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

fn f32_at(b: &[u8], i: usize) -> f32 {
    f32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Parses a `.hair` file: the header, the arrays its flags announce, then the strands.
fn parse(path: &Path, bytes: &[u8]) -> Result<Strands, FormatError> {
    let header = read_header(path, bytes)?;
    let arrays = read_arrays(path, bytes, &header)?;
    build_strands(path, &header, &arrays)
}

/// The fields of the 128-byte header that reading uses.
struct HairHeader {
    hair_count: usize,
    point_count: usize,
    flags: u32,
    /// Segments per hair when the file has no segments array.
    default_segments: usize,
    /// Thickness of every hair when the file has no thickness array.
    default_thickness: f32,
    /// Colour of every hair when the file has no colour array.
    default_color: [f32; 3],
}

/// Reads and checks the header: signature, size, and flags that include the points array and
/// nothing unknown.
fn read_header(path: &Path, bytes: &[u8]) -> Result<HairHeader, FormatError> {
    if bytes.len() < 4 || &bytes[..4] != b"HAIR" {
        return Err(FormatError::at(
            path,
            Position::Byte(0),
            "expected the signature \"HAIR\": not a .hair file",
        ));
    }
    if bytes.len() < HEADER {
        return Err(FormatError::at(
            path,
            Position::Byte(bytes.len() as u64),
            format!(
                "file ends inside the 128-byte header ({} bytes)",
                bytes.len()
            ),
        ));
    }
    let header = HairHeader {
        hair_count: u32_at(bytes, 4) as usize,
        point_count: u32_at(bytes, 8) as usize,
        flags: u32_at(bytes, 12),
        default_segments: u32_at(bytes, 16) as usize,
        default_thickness: f32_at(bytes, 20),
        default_color: [f32_at(bytes, 28), f32_at(bytes, 32), f32_at(bytes, 36)],
    };
    let flags = header.flags;
    if flags & FLAG_POINTS == 0 {
        return Err(FormatError::at(
            path,
            Position::Byte(12),
            "flags say the file has no points array (bit 2 unset): nothing to read",
        ));
    }
    if flags & !31 != 0 {
        return Err(FormatError::at(
            path,
            Position::Byte(12),
            format!(
                "unknown flag bits {:#x} (expected only bits 1, 2, 4, 8, 16)",
                flags & !31
            ),
        ));
    }
    Ok(header)
}

/// The arrays of the file body; thickness and colour only when the flags announce them.
struct HairArrays {
    /// Segments of each hair.
    segments: Vec<usize>,
    /// Point coordinates, three per point.
    points: Vec<f32>,
    /// Thickness per point.
    thickness: Option<Vec<f32>>,
    /// Colour per point, three per point.
    colors: Option<Vec<f32>>,
}

/// Reads the arrays after the header in file order (segments, points, thickness, transparency,
/// colours), checking the point count, finite points and that nothing follows the last array.
fn read_arrays(path: &Path, bytes: &[u8], header: &HairHeader) -> Result<HairArrays, FormatError> {
    let (flags, point_count) = (header.flags, header.point_count);
    let mut cur = Cursor {
        path,
        bytes,
        pos: HEADER,
    };
    let segments = read_segments(&mut cur, header)?;
    let points_start = cur.pos;
    let points = f32s(cur.take(point_count.saturating_mul(12), "points array")?);
    if let Some(i) = points.iter().position(|v| !v.is_finite()) {
        return Err(FormatError::at(
            path,
            Position::Byte((points_start + 4 * i) as u64),
            "expected a finite point coordinate",
        ));
    }
    let thickness = if flags & FLAG_THICKNESS != 0 {
        Some(f32s(
            cur.take(point_count.saturating_mul(4), "thickness array")?,
        ))
    } else {
        None
    };
    if flags & FLAG_TRANSPARENCY != 0 {
        cur.take(point_count.saturating_mul(4), "transparency array")?;
    }
    let colors = if flags & FLAG_COLORS != 0 {
        Some(f32s(
            cur.take(point_count.saturating_mul(12), "colour array")?,
        ))
    } else {
        None
    };
    if cur.pos != bytes.len() {
        return Err(FormatError::at(
            path,
            Position::Byte(cur.pos as u64),
            format!(
                "{} unexpected bytes after the last array (header counts and flags disagree with the file size)",
                bytes.len() - cur.pos
            ),
        ));
    }
    Ok(HairArrays {
        segments,
        points,
        thickness,
        colors,
    })
}

/// The segments of each hair (from the segments array, or the header default), which must add
/// up to the header's point count.
fn read_segments(cur: &mut Cursor<'_>, header: &HairHeader) -> Result<Vec<usize>, FormatError> {
    let (flags, hair_count, point_count) = (header.flags, header.hair_count, header.point_count);
    let segments: Vec<usize> = if flags & FLAG_SEGMENTS != 0 {
        cur.take(hair_count.saturating_mul(2), "segments array")?
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]) as usize)
            .collect()
    } else {
        vec![header.default_segments; hair_count]
    };
    let total: usize = segments.iter().map(|s| s + 1).sum();
    if total != point_count {
        let at = if flags & FLAG_SEGMENTS != 0 {
            HEADER
        } else {
            16
        };
        return Err(FormatError::at(
            cur.path,
            Position::Byte(at as u64),
            format!(
                "segment counts add up to {total} points over {hair_count} hairs, but the header says {point_count} points"
            ),
        ));
    }
    Ok(segments)
}

/// The strands, each with the thickness and colour of its root point (or the header defaults);
/// fails on non-finite thickness or colour values.
fn build_strands(
    path: &Path,
    header: &HairHeader,
    arrays: &HairArrays,
) -> Result<Strands, FormatError> {
    let (points, thickness, colors) = (&arrays.points, &arrays.thickness, &arrays.colors);
    let mut strands = Strands::new();
    strands.points.reserve(header.point_count);
    let mut first = 0usize;
    for &seg in &arrays.segments {
        let n = seg + 1;
        let pts: Vec<Vec3> = (first..first + n)
            .map(|i| Vec3::new(points[3 * i], points[3 * i + 1], points[3 * i + 2]))
            .collect();
        let width = thickness
            .as_ref()
            .map_or(header.default_thickness, |t| t[first]);
        let color = colors.as_ref().map_or(header.default_color, |c| {
            [c[3 * first], c[3 * first + 1], c[3 * first + 2]]
        });
        strands.push(&pts, 0, width, color);
        first += n;
    }
    if strands
        .width
        .iter()
        .chain(strands.color.iter().flatten())
        .any(|v| !v.is_finite())
    {
        return Err(FormatError::invalid(
            path,
            "non-finite thickness or colour values",
        ));
    }
    Ok(strands)
}

/// Writes a `.hair` file (segments, points, thickness and colour arrays).
pub fn write_hair(path: impl AsRef<Path>, strands: &Strands) -> Result<(), FormatError> {
    let path = path.as_ref();
    let bytes = encode(path, strands)?;
    write_bytes(path, &bytes)
}

fn encode(path: &Path, strands: &Strands) -> Result<Vec<u8>, FormatError> {
    let n = strands.len();
    if strands.starts.first().copied().unwrap_or(0) != 0
        || strands.starts.windows(2).any(|w| w[0] > w[1])
        || strands.starts.last().copied().unwrap_or(0) as usize != strands.points.len()
        || strands.width.len() != n
        || strands.color.len() != n
    {
        return Err(FormatError::invalid(
            path,
            "inconsistent strand set (starts / width / colour arrays do not match the points)",
        ));
    }
    check_finite(
        path,
        "point coordinate",
        strands.points.iter().flat_map(|p| p.to_array()),
    )?;
    check_finite(path, "strand width", strands.width.iter().copied())?;
    check_finite(
        path,
        "strand colour",
        strands.color.iter().flatten().copied(),
    )?;
    let point_count = u32::try_from(strands.points.len())
        .map_err(|_| FormatError::invalid(path, "more than 2^32 - 1 points"))?;
    let hair_count = n as u32;
    let mut segs = Vec::with_capacity(n);
    for s in 0..n {
        let len = strands.strand(s).len();
        if len == 0 || len > 65536 {
            return Err(FormatError::invalid(
                path,
                format!("strand {s} has {len} points: .hair stores 1 to 65536 points per strand"),
            ));
        }
        segs.push((len - 1) as u16);
    }
    let default_width = strands.width.first().copied().unwrap_or(1.0);
    let default_color = strands.color.first().copied().unwrap_or([1.0; 3]);
    // An array is written unless the header's default holds every value (compared bit for
    // bit, so that reading gives back exactly what was written).
    let varies = |differs: bool, flag: u32| if differs { flag } else { 0 };
    let flags = FLAG_POINTS
        | varies(segs.windows(2).any(|w| w[0] != w[1]), FLAG_SEGMENTS)
        | varies(
            strands
                .width
                .iter()
                .any(|w| w.to_bits() != default_width.to_bits()),
            FLAG_THICKNESS,
        )
        | varies(
            strands
                .color
                .iter()
                .flatten()
                .zip(default_color.iter().cycle())
                .any(|(c, d)| c.to_bits() != d.to_bits()),
            FLAG_COLORS,
        );
    let mut out = Vec::with_capacity(HEADER + 2 * n + 28 * strands.points.len());
    out.extend_from_slice(b"HAIR");
    out.extend_from_slice(&hair_count.to_le_bytes());
    out.extend_from_slice(&point_count.to_le_bytes());
    out.extend_from_slice(&flags.to_le_bytes());
    let default_segments = segs.first().copied().unwrap_or(0) as u32;
    out.extend_from_slice(&default_segments.to_le_bytes());
    out.extend_from_slice(&default_width.to_le_bytes());
    out.extend_from_slice(&1.0f32.to_le_bytes()); // default transparency (unused)
    for c in default_color {
        out.extend_from_slice(&c.to_le_bytes());
    }
    let mut info = [0u8; 88];
    info[..INFO.len()].copy_from_slice(INFO.as_bytes());
    out.extend_from_slice(&info);
    debug_assert_eq!(out.len(), HEADER);
    if flags & FLAG_SEGMENTS != 0 {
        for s in &segs {
            out.extend_from_slice(&s.to_le_bytes());
        }
    }
    for p in &strands.points {
        for v in p.to_array() {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    if flags & FLAG_THICKNESS != 0 {
        for s in 0..n {
            for _ in 0..strands.strand(s).len() {
                out.extend_from_slice(&strands.width[s].to_le_bytes());
            }
        }
    }
    if flags & FLAG_COLORS != 0 {
        for s in 0..n {
            for _ in 0..strands.strand(s).len() {
                for v in strands.color[s] {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A small strand set with varied lengths, widths and colours.
    pub(crate) fn sample() -> Strands {
        let mut s = Strands::new();
        for k in 0..7u32 {
            let n = 2 + (k as usize * 3) % 9;
            let pts: Vec<Vec3> = (0..n)
                .map(|i| {
                    Vec3::new(
                        k as f32 * 0.1,
                        i as f32 * 0.01 + 1e-7 * k as f32,
                        -0.3 * i as f32,
                    )
                })
                .collect();
            s.push(
                &pts,
                (k % 3) as u16,
                0.001 * (k + 1) as f32,
                [0.1 * k as f32, 0.5, 1.0 / 3.0],
            );
        }
        s
    }

    #[test]
    fn round_trip_exact_and_deterministic() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x/s.hair");
        let s = sample();
        write_hair(&p, &s).unwrap();
        let back = read_hair(&p).unwrap();
        assert_eq!(back.points, s.points);
        assert_eq!(back.starts, s.starts);
        assert_eq!(back.width, s.width);
        assert_eq!(back.color, s.color);
        assert!(back.part.iter().all(|&p| p == 0) && back.part_names.is_empty());
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..4], b"HAIR");
        assert_eq!(bytes.len(), 128 + 2 * 7 + 28 * s.points.len());
        write_hair(&p, &back).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), bytes);
        // Empty sets are fine too.
        write_hair(&p, &Strands::new()).unwrap();
        assert!(read_hair(&p).unwrap().is_empty());
    }

    /// Arrays that the header's defaults can hold are left out, one by one,
    /// and the file still reads back exactly.
    #[test]
    fn uniform_arrays_are_left_out() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("u.hair");
        let mut s = Strands::new();
        for k in 0..5 {
            let pts: Vec<Vec3> = (0..4).map(|i| Vec3::new(k as f32, i as f32, 0.5)).collect();
            s.push(&pts, 0, 0.02 + 0.01 * (k % 2) as f32, [0.3, 0.2, 0.1]);
        }
        let points = s.points.len();
        // Same segment count and colour everywhere, widths vary: points and thickness only.
        write_hair(&p, &s).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(u32::from_le_bytes(bytes[12..16].try_into().unwrap()), 2 | 4);
        assert_eq!(bytes.len(), 128 + 16 * points);
        let back = read_hair(&p).unwrap();
        assert_eq!(
            (back.points, back.starts),
            (s.points.clone(), s.starts.clone())
        );
        assert_eq!((back.width, back.color), (s.width.clone(), s.color.clone()));
        // One different colour brings the colour array back; -0.0 is not 0.0.
        s.color[3] = [0.3, 0.2, -0.0];
        s.color[0] = [0.3, 0.2, 0.0];
        for c in &mut s.color[1..3] {
            *c = [0.3, 0.2, 0.0];
        }
        s.color[4] = [0.3, 0.2, 0.0];
        write_hair(&p, &s).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(
            u32::from_le_bytes(bytes[12..16].try_into().unwrap()),
            2 | 4 | 16
        );
        let back = read_hair(&p).unwrap();
        assert_eq!(back.color[3][2].to_bits(), (-0.0f32).to_bits());
    }

    #[test]
    fn defaults_used_without_arrays() {
        // A hand-made file: 2 hairs of 2 segments, points only, default thickness and colour.
        let mut b = Vec::new();
        b.extend_from_slice(b"HAIR");
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(&6u32.to_le_bytes());
        b.extend_from_slice(&(FLAG_POINTS | FLAG_TRANSPARENCY).to_le_bytes());
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(&0.25f32.to_le_bytes());
        b.extend_from_slice(&0.5f32.to_le_bytes());
        for c in [0.1f32, 0.2, 0.3] {
            b.extend_from_slice(&c.to_le_bytes());
        }
        b.extend_from_slice(&[0u8; 88]);
        for i in 0..18 {
            b.extend_from_slice(&(i as f32).to_le_bytes());
        }
        for _ in 0..6 {
            b.extend_from_slice(&0.9f32.to_le_bytes());
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.hair");
        std::fs::write(&p, &b).unwrap();
        let s = read_hair(&p).unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(s.strand(1)[0], Vec3::new(9.0, 10.0, 11.0));
        assert_eq!(s.width, vec![0.25, 0.25]);
        assert_eq!(s.color[1], [0.1, 0.2, 0.3]);
    }

    #[test]
    fn truncated_and_malformed_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.hair");
        write_hair(&p, &sample()).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        // Truncated in the points array.
        std::fs::write(&p, &bytes[..200]).unwrap();
        let e = read_hair(&p).unwrap_err();
        assert_eq!(e.position(), Some(&Position::Byte(200)), "{e}");
        assert!(
            e.to_string().contains("t.hair") && e.to_string().contains("points array"),
            "{e}"
        );
        // Truncated in the header.
        std::fs::write(&p, &bytes[..60]).unwrap();
        assert_eq!(
            read_hair(&p).unwrap_err().position(),
            Some(&Position::Byte(60))
        );
        // Wrong signature.
        let mut bad = bytes.clone();
        bad[0] = b'X';
        std::fs::write(&p, &bad).unwrap();
        assert_eq!(
            read_hair(&p).unwrap_err().position(),
            Some(&Position::Byte(0))
        );
        // Point count disagreeing with the segments.
        let mut bad = bytes.clone();
        bad[8] = bad[8].wrapping_add(1);
        std::fs::write(&p, &bad).unwrap();
        let e = read_hair(&p).unwrap_err();
        assert!(e.to_string().contains("header says"), "{e}");
        // Trailing garbage.
        let mut bad = bytes.clone();
        bad.extend_from_slice(&[0; 4]);
        std::fs::write(&p, &bad).unwrap();
        assert_eq!(
            read_hair(&p).unwrap_err().position(),
            Some(&Position::Byte(bytes.len() as u64))
        );
    }

    #[test]
    fn unwritable_sets_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("u.hair");
        let mut s = sample();
        s.width[2] = f32::NAN;
        assert!(write_hair(&p, &s).is_err());
        let mut s = Strands::new();
        s.push(&vec![Vec3::ZERO; 70000], 0, 1.0, [1.0; 3]);
        assert!(write_hair(&p, &s).is_err());
        assert!(!p.exists());
    }
}
