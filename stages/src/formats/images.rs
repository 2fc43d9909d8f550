//! Images: PNG (8 and 16 bit, gray / gray+alpha / RGB / RGBA, palettes expanded), OpenEXR, and
//! JPEG for reading only (real captures converted from COLMAP usually come as JPEG; we never write
//! lossy files).
//!
//! In memory every image is an [`ImageF32`]: row-major, top row first, interleaved channels.
//!
//! PNG. Reading maps integer samples to [0, 1] (`v / 255` or `v / 65535`) and keeps the file's
//! channel count (1 gray, 2 gray+alpha, 3 RGB, 4 RGBA). Values are taken as stored: no sRGB to
//! linear conversion happens here (stages that need linear light convert explicitly, so that masks
//! and data maps stored as PNG are never distorted). Writing clamps to [0, 1], rounds to the
//! nearest of 256 levels and writes 8-bit gray / gray+alpha / RGB / RGBA for 1 / 2 / 3 / 4
//! channels. NaN or infinite samples are refused (clamping would hide a bug upstream).
//!
//! EXR. Float data of any range: renders, depth, masks and scalar maps. Reading takes the first
//! layer at full resolution; channels are ordered `R G B A` (any subset, in that order) or `Y A`
//! (gray); a single channel of any name (`Z`, `depth`, ...) reads as one channel. Samples of any
//! EXR sample type are converted to f32. Writing stores f32 samples, named `Y` / `Y A` / `R G B` /
//! `R G B A` for 1 / 2 / 3 / 4 channels, ZIP-compressed (lossless), single-threaded so the bytes
//! never depend on the thread count. EXR can store NaN and infinities, but no stage means to
//! (depth backgrounds, renders and orientation maps are finite by construction), so writing
//! refuses them like the PNG writer: a NaN in an output is a bug upstream, reported at the write
//! instead of flowing into the next stage. Reading accepts them (a user's file may hold them; the
//! stages that read images treat non-finite samples themselves).
//!
//! Decoder errors rarely say where they happened; both readers decode from memory through a reader
//! that tracks the furthest byte consumed, and report that offset with the decoder's message.

use std::path::Path;

use exr::prelude as ex;
use exr::prelude::traits::*;
use image::{DynamicImage, ImageDecoder};

use super::{
    check_finite, extension, read_bytes, write_bytes, FormatError, Position, TrackingReader,
};
use crate::data::image::ImageF32;

const PNG_SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];

/// The photo extensions [`read_image`] reads (lower case; file names match case-insensitively).
pub const IMAGE_EXTENSIONS: [&str; 4] = ["png", "jpg", "jpeg", "exr"];

/// Reads an image by file extension (`.png`, `.jpg`/`.jpeg` or `.exr`, case-insensitive).
pub fn read_image(path: impl AsRef<Path>) -> Result<ImageF32, FormatError> {
    let path = path.as_ref();
    match extension(path).as_str() {
        "png" => read_png(path),
        "jpg" | "jpeg" => read_jpeg(path),
        "exr" => read_exr(path),
        other => Err(FormatError::invalid(
            path,
            format!("unsupported image extension `{other}`: expected .png, .jpg, .jpeg or .exr"),
        )),
    }
}

/// Writes an image by file extension (`.png` or `.exr`).
pub fn write_image(path: impl AsRef<Path>, image: &ImageF32) -> Result<(), FormatError> {
    let path = path.as_ref();
    match extension(path).as_str() {
        "png" => write_png(path, image),
        "exr" => write_exr(path, image),
        other => Err(FormatError::invalid(
            path,
            format!("unsupported image extension `{other}`: expected .png or .exr"),
        )),
    }
}

/// Width and height from the image header only (PNG: the IHDR chunk; JPEG: the frame header;
/// EXR: the header).
pub fn image_size(path: impl AsRef<Path>) -> Result<(u32, u32), FormatError> {
    let path = path.as_ref();
    match extension(path).as_str() {
        "png" => {
            let mut head = [0u8; 24];
            let mut f = std::fs::File::open(path).map_err(|e| FormatError::io(path, e))?;
            let n = read_up_to(&mut f, &mut head).map_err(|e| FormatError::io(path, e))?;
            png_header(path, &head[..n])
        }
        "jpg" | "jpeg" => jpeg_size(path),
        "exr" => {
            let meta =
                ex::MetaData::read_from_file(path, false).map_err(|e| exr_error(path, e, None))?;
            let header = meta
                .headers
                .first()
                .ok_or_else(|| FormatError::invalid(path, "EXR file has no header (no layers)"))?;
            let s = header.layer_size;
            Ok((s.0 as u32, s.1 as u32))
        }
        other => Err(FormatError::invalid(
            path,
            format!("unsupported image extension `{other}`: expected .png or .exr"),
        )),
    }
}

/// Width and height from a JPEG's SOF marker.
fn jpeg_size(path: &Path) -> Result<(u32, u32), FormatError> {
    let bytes = read_bytes(path)?;
    if bytes.len() < 2 || bytes[0] != 0xFF || bytes[1] != 0xD8 {
        return Err(FormatError::at(
            path,
            Position::Byte(0),
            "expected the JPEG SOI marker FF D8",
        ));
    }
    let mut i = 2usize;
    loop {
        // Skip fill bytes, then read a marker.
        while i < bytes.len() && bytes[i] == 0xFF && bytes.get(i + 1) == Some(&0xFF) {
            i += 1;
        }
        if i + 4 > bytes.len() || bytes[i] != 0xFF {
            return Err(FormatError::at(
                path,
                Position::Byte(i as u64),
                "expected a JPEG marker segment before the frame header (truncated file?)",
            ));
        }
        let marker = bytes[i + 1];
        let len = u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]) as usize;
        let is_sof = (0xC0..=0xCF).contains(&marker) && ![0xC4, 0xC8, 0xCC].contains(&marker);
        if is_sof {
            if i + 9 > bytes.len() {
                return Err(FormatError::at(
                    path,
                    Position::Byte(i as u64),
                    "truncated JPEG frame header",
                ));
            }
            let h = u16::from_be_bytes([bytes[i + 5], bytes[i + 6]]) as u32;
            let w = u16::from_be_bytes([bytes[i + 7], bytes[i + 8]]) as u32;
            return Ok((w, h));
        }
        if len < 2 {
            return Err(FormatError::at(
                path,
                Position::Byte(i as u64 + 2),
                "invalid JPEG segment length",
            ));
        }
        i += 2 + len;
    }
}

fn read_up_to(r: &mut impl std::io::Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// Checks the PNG signature and IHDR chunk; returns (width, height).
fn png_header(path: &Path, bytes: &[u8]) -> Result<(u32, u32), FormatError> {
    if bytes.len() < 8 || bytes[..8] != PNG_SIGNATURE {
        let n = bytes.len().min(8);
        let off = (0..n).find(|&i| bytes[i] != PNG_SIGNATURE[i]).unwrap_or(n);
        return Err(FormatError::at(
            path,
            Position::Byte(off as u64),
            "expected the 8-byte PNG signature (\\x89PNG\\r\\n\\x1a\\n): not a PNG file or truncated",
        ));
    }
    if bytes.len() < 24 {
        return Err(FormatError::at(
            path,
            Position::Byte(bytes.len() as u64),
            "file ends inside the IHDR chunk (expected width and height at bytes 16..24)",
        ));
    }
    if &bytes[12..16] != b"IHDR" {
        return Err(FormatError::at(
            path,
            Position::Byte(12),
            "expected the IHDR chunk right after the signature",
        ));
    }
    let w = u32::from_be_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]);
    let h = u32::from_be_bytes([bytes[20], bytes[21], bytes[22], bytes[23]]);
    Ok((w, h))
}

/// Reads a PNG into [0, 1] floats, keeping its channel count.
pub fn read_png(path: impl AsRef<Path>) -> Result<ImageF32, FormatError> {
    let path = path.as_ref();
    let bytes = read_bytes(path)?;
    png_header(path, &bytes)?;
    let mut reader = TrackingReader::new(&bytes);
    let result = image::codecs::png::PngDecoder::new(&mut reader).and_then(|mut d| {
        // The decoder's default allocation cap (512 MiB) turns a corrupt header claiming a huge
        // image into an error instead of an out-of-memory abort; real views are far smaller.
        d.set_limits(image::Limits::default())?;
        DynamicImage::from_decoder(d)
    });
    let img = result.map_err(|e| {
        FormatError::at(
            path,
            Position::Byte(reader.furthest()),
            format!("PNG decoding failed near here: {e}"),
        )
    })?;
    let (w, h) = (img.width(), img.height());
    let (channels, data): (u32, Vec<f32>) = match img {
        DynamicImage::ImageLuma8(b) => (1, scale8(b.as_raw())),
        DynamicImage::ImageLumaA8(b) => (2, scale8(b.as_raw())),
        DynamicImage::ImageRgb8(b) => (3, scale8(b.as_raw())),
        DynamicImage::ImageRgba8(b) => (4, scale8(b.as_raw())),
        DynamicImage::ImageLuma16(b) => (1, scale16(b.as_raw())),
        DynamicImage::ImageLumaA16(b) => (2, scale16(b.as_raw())),
        DynamicImage::ImageRgb16(b) => (3, scale16(b.as_raw())),
        DynamicImage::ImageRgba16(b) => (4, scale16(b.as_raw())),
        DynamicImage::ImageRgb32F(b) => (3, b.into_raw()),
        DynamicImage::ImageRgba32F(b) => (4, b.into_raw()),
        other => {
            return Err(FormatError::invalid(
                path,
                format!("unsupported PNG pixel layout {:?}", other.color()),
            ))
        }
    };
    Ok(ImageF32 {
        width: w,
        height: h,
        channels,
        data,
    })
}

/// Reads a JPEG (real captures) into [0, 1] floats: 1 channel for gray, 3 for colour (CMYK is
/// converted to RGB by the decoder). Read-only: we never write lossy images.
pub fn read_jpeg(path: impl AsRef<Path>) -> Result<ImageF32, FormatError> {
    let path = path.as_ref();
    let bytes = read_bytes(path)?;
    if bytes.len() < 2 || bytes[..2] != [0xFF, 0xD8] {
        return Err(FormatError::at(
            path,
            Position::Byte(0),
            "expected the JPEG start-of-image marker FF D8: not a JPEG file",
        ));
    }
    let mut reader = TrackingReader::new(&bytes);
    let result = image::codecs::jpeg::JpegDecoder::new(&mut reader).and_then(|mut d| {
        d.set_limits(image::Limits::default())?;
        DynamicImage::from_decoder(d)
    });
    let img = result.map_err(|e| {
        FormatError::at(
            path,
            Position::Byte(reader.furthest()),
            format!("JPEG decoding failed near here: {e}"),
        )
    })?;
    let (width, height) = (img.width(), img.height());
    let (channels, data) = match img {
        DynamicImage::ImageLuma8(b) => (1, scale8(b.as_raw())),
        other => (3, scale8(other.to_rgb8().as_raw())),
    };
    Ok(ImageF32 {
        width,
        height,
        channels,
        data,
    })
}

fn scale8(v: &[u8]) -> Vec<f32> {
    v.iter().map(|&x| x as f32 / 255.0).collect()
}

fn scale16(v: &[u16]) -> Vec<f32> {
    v.iter().map(|&x| x as f32 / 65535.0).collect()
}

fn check_shape(path: &Path, image: &ImageF32) -> Result<(), FormatError> {
    if !(1..=4).contains(&image.channels) {
        return Err(FormatError::invalid(
            path,
            format!(
                "cannot write an image with {} channels: expected 1 to 4",
                image.channels
            ),
        ));
    }
    let expected = image.width as u64 * image.height as u64 * image.channels as u64;
    if image.data.len() as u64 != expected {
        return Err(FormatError::invalid(
            path,
            format!(
                "image data has {} samples, expected {} x {} x {} = {expected}",
                image.data.len(),
                image.width,
                image.height,
                image.channels
            ),
        ));
    }
    if image.width == 0 || image.height == 0 {
        return Err(FormatError::invalid(
            path,
            format!(
                "cannot write an empty {} x {} image",
                image.width, image.height
            ),
        ));
    }
    Ok(())
}

/// Writes an 8-bit PNG (gray, gray+alpha, RGB or RGBA for 1 to 4 channels), clamping to [0, 1].
pub fn write_png(path: impl AsRef<Path>, image: &ImageF32) -> Result<(), FormatError> {
    let path = path.as_ref();
    check_shape(path, image)?;
    check_finite(path, "sample", image.data.iter().copied())?;
    let raw: Vec<u8> = image
        .data
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let color = match image.channels {
        1 => image::ExtendedColorType::L8,
        2 => image::ExtendedColorType::La8,
        3 => image::ExtendedColorType::Rgb8,
        _ => image::ExtendedColorType::Rgba8,
    };
    let mut out = Vec::new();
    let encoder = image::codecs::png::PngEncoder::new_with_quality(
        &mut out,
        image::codecs::png::CompressionType::Default,
        image::codecs::png::FilterType::Adaptive,
    );
    image::ImageEncoder::write_image(encoder, &raw, image.width, image.height, color)
        .map_err(|e| FormatError::invalid(path, format!("PNG encoding failed: {e}")))?;
    write_bytes(path, &out)
}

fn exr_error(path: &Path, e: ex::Error, offset: Option<u64>) -> FormatError {
    match (e, offset) {
        (ex::Error::Io(io), None) => FormatError::io(path, io),
        (ex::Error::Io(io), Some(off)) => FormatError::at(
            path,
            Position::Byte(off),
            format!("EXR file ends or breaks near here ({io})"),
        ),
        (other, Some(off)) => FormatError::at(
            path,
            Position::Byte(off),
            format!("EXR decoding failed near here: {other}"),
        ),
        (other, None) => FormatError::invalid(path, format!("EXR: {other}")),
    }
}

/// Reads the first layer of an EXR file as f32 (see the module doc for channel order).
pub fn read_exr(path: impl AsRef<Path>) -> Result<ImageF32, FormatError> {
    let path = path.as_ref();
    let bytes = read_bytes(path)?;
    let mut reader = TrackingReader::new(&bytes);
    let result = ex::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .non_parallel()
        .from_buffered(&mut reader);
    let image = result.map_err(|e| exr_error(path, e, Some(reader.furthest())))?;
    let layer = &image.layer_data;
    let (w, h) = (layer.size.0, layer.size.1);
    let list = &layer.channel_data.list;
    let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
    let order = channel_order(&names).ok_or_else(|| {
        FormatError::invalid(
            path,
            format!(
                "unsupported EXR channels {names:?}: expected R G B A (any subset), Y, Y A, or one channel"
            ),
        )
    })?;
    let c = order.len();
    let planes: Vec<Vec<f32>> = order
        .iter()
        .map(|&i| list[i].sample_data.values_as_f32().collect())
        .collect();
    let n = w * h;
    if planes.iter().any(|p| p.len() != n) {
        return Err(FormatError::invalid(
            path,
            "EXR channel sizes do not match the layer size",
        ));
    }
    let mut data = vec![0.0f32; n * c];
    for (k, plane) in planes.iter().enumerate() {
        for (i, &v) in plane.iter().enumerate() {
            data[i * c + k] = v;
        }
    }
    Ok(ImageF32 {
        width: w as u32,
        height: h as u32,
        channels: c as u32,
        data,
    })
}

/// Indices into `names` in our interleaving order, or None for an unsupported set.
fn channel_order(names: &[String]) -> Option<Vec<usize>> {
    let find = |n: &str| names.iter().position(|x| x == n);
    if names.len() == 1 {
        return Some(vec![0]);
    }
    if names.len() == 2 {
        if let (Some(y), Some(a)) = (find("Y"), find("A")) {
            return Some(vec![y, a]);
        }
    }
    let mut order = Vec::new();
    for n in ["R", "G", "B", "A"] {
        if let Some(i) = find(n) {
            order.push(i);
        }
    }
    (order.len() == names.len() && !order.is_empty() && order.len() <= 4).then_some(order)
}

/// Writes an f32 EXR (`Y`, `Y A`, `R G B` or `R G B A` for 1 to 4 channels).
pub fn write_exr(path: impl AsRef<Path>, image: &ImageF32) -> Result<(), FormatError> {
    let path = path.as_ref();
    check_shape(path, image)?;
    check_finite(path, "sample", image.data.iter().copied())?;
    let names: &[&str] = match image.channels {
        1 => &["Y"],
        2 => &["Y", "A"],
        3 => &["R", "G", "B"],
        _ => &["R", "G", "B", "A"],
    };
    let c = image.channels as usize;
    let channels: Vec<ex::AnyChannel<ex::FlatSamples>> = names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let plane: Vec<f32> = image.data.iter().skip(k).step_by(c).copied().collect();
            ex::AnyChannel::new(*name, ex::FlatSamples::F32(plane))
        })
        .collect();
    let layer = ex::Layer::new(
        (image.width as usize, image.height as usize),
        ex::LayerAttributes::default(),
        ex::Encoding {
            compression: ex::Compression::ZIP16,
            ..ex::Encoding::default()
        },
        ex::AnyChannels::sort(ex::SmallVec::from_vec(channels)),
    );
    let img = ex::Image::from_layer(layer);
    let mut out = std::io::Cursor::new(Vec::new());
    ex::WritableImage::write(&img)
        .non_parallel()
        .to_buffered(&mut out)
        .map_err(|e| FormatError::invalid(path, format!("EXR encoding failed: {e}")))?;
    write_bytes(path, &out.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(w: u32, h: u32, c: u32) -> ImageF32 {
        let mut img = ImageF32::new(w, h, c);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = ((i * 37 + 11) % 256) as f32 / 255.0;
        }
        img
    }

    #[test]
    fn png_round_trip_all_channel_counts() {
        let dir = tempfile::tempdir().unwrap();
        for c in 1..=4 {
            let p = dir.path().join(format!("a/{c}.png"));
            let img = pattern(7, 5, c);
            write_png(&p, &img).unwrap();
            let back = read_png(&p).unwrap();
            assert_eq!((back.width, back.height, back.channels), (7, 5, c));
            // 8-bit levels are exact after the /255 mapping.
            assert_eq!(back.data, img.data, "channels {c}");
            assert_eq!(image_size(&p).unwrap(), (7, 5));
            let bytes = std::fs::read(&p).unwrap();
            write_png(&p, &back).unwrap();
            assert_eq!(std::fs::read(&p).unwrap(), bytes, "deterministic bytes");
        }
    }

    #[test]
    fn png_write_clamps_and_rounds() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.png");
        let img = ImageF32 {
            width: 4,
            height: 1,
            channels: 1,
            data: vec![-0.5, 2.0, 0.5, 0.1],
        };
        write_png(&p, &img).unwrap();
        let back = read_png(&p).unwrap();
        let expect = [0.0, 1.0, 128.0 / 255.0, 26.0 / 255.0];
        assert_eq!(back.data, expect);
        let mut bad = img.clone();
        bad.data[2] = f32::NAN;
        assert!(write_png(&p, &bad).is_err());
    }

    #[test]
    fn png_16_bit_reads_to_unit_range() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.png");
        let buf: image::ImageBuffer<image::Rgb<u16>, Vec<u16>> =
            image::ImageBuffer::from_raw(2, 1, vec![0, 65535, 32768, 1, 2, 3]).unwrap();
        buf.save(&p).unwrap();
        let back = read_png(&p).unwrap();
        assert_eq!(back.channels, 3);
        assert_eq!(back.data[1], 1.0);
        assert!((back.data[2] - 32768.0 / 65535.0).abs() < 1e-7);
    }

    #[test]
    fn png_truncated_and_malformed() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.png");
        write_png(&p, &pattern(64, 64, 3)).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_png(&p).unwrap_err();
        let s = e.to_string();
        assert!(s.contains("t.png") && s.contains("byte"), "{s}");
        std::fs::write(&p, b"GIF89a......").unwrap();
        let e = read_png(&p).unwrap_err();
        assert_eq!(e.position(), Some(&Position::Byte(0)), "{e}");
        std::fs::write(&p, &bytes[..20]).unwrap();
        let e = read_png(&p).unwrap_err();
        assert_eq!(e.position(), Some(&Position::Byte(20)), "{e}");
        assert!(image_size(&p).is_err());
    }

    #[test]
    fn exr_round_trip_exact_floats() {
        let dir = tempfile::tempdir().unwrap();
        for c in 1..=4 {
            let p = dir.path().join(format!("e{c}.exr"));
            let mut img = pattern(9, 4, c);
            img.data[0] = -12.5;
            img.data[1] = 1e20;
            write_exr(&p, &img).unwrap();
            let back = read_exr(&p).unwrap();
            assert_eq!(back, img, "channels {c}");
            assert_eq!(image_size(&p).unwrap(), (9, 4));
            let bytes = std::fs::read(&p).unwrap();
            write_exr(&p, &back).unwrap();
            assert_eq!(std::fs::read(&p).unwrap(), bytes);
        }
    }

    #[test]
    fn exr_truncated_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.exr");
        write_exr(&p, &pattern(32, 32, 3)).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let e = read_exr(&p).unwrap_err();
        assert!(e.to_string().contains("t.exr"), "{e}");
        std::fs::write(&p, b"not an exr").unwrap();
        let e = read_exr(&p).unwrap_err();
        assert!(e.position().is_some(), "{e}");
    }

    #[test]
    fn jpeg_header_size() {
        let dir = tempfile::tempdir().unwrap();
        // A JPEG header is enough for the size.
        let mut jpg = vec![0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x04, 0, 0];
        jpg.extend_from_slice(&[0xFF, 0xC0, 0x00, 0x11, 8, 0x01, 0xE0, 0x02, 0x80, 3]);
        std::fs::write(dir.path().join("z.jpg"), &jpg).unwrap();
        assert_eq!(jpeg_size(&dir.path().join("z.jpg")).unwrap(), (640, 480));
        std::fs::write(dir.path().join("z.jpg"), &jpg[..6]).unwrap();
        assert!(jpeg_size(&dir.path().join("z.jpg")).is_err());
    }

    #[test]
    fn jpeg_reads_real_encoder_output() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("photo.JPG");
        let (w, h) = (40u32, 24u32);
        let raw: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                [(x * 6) as u8, (y * 10) as u8, 128]
            })
            .collect();
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95)
            .encode(&raw, w, h, image::ExtendedColorType::Rgb8)
            .unwrap();
        std::fs::write(&p, &out).unwrap();
        assert_eq!(image_size(&p).unwrap(), (w, h));
        let img = read_image(&p).unwrap();
        assert_eq!((img.width, img.height, img.channels), (w, h, 3));
        // Lossy, but close: mean absolute error well under 2 levels.
        let err: f32 = img
            .data
            .iter()
            .zip(&raw)
            .map(|(a, &b)| (a - b as f32 / 255.0).abs())
            .sum::<f32>()
            / raw.len() as f32;
        assert!(err < 2.0 / 255.0, "{err}");
        std::fs::write(&p, &out[..out.len() / 2]).unwrap();
        let e = read_jpeg(&p);
        // zune-jpeg pads truncated scans; either an error naming the file or a full-size image.
        match e {
            Err(e) => assert!(e.to_string().contains("photo.JPG"), "{e}"),
            Ok(img) => assert_eq!((img.width, img.height), (w, h)),
        }
        std::fs::write(&p, b"\x89PNG").unwrap();
        assert_eq!(
            read_jpeg(&p).unwrap_err().position(),
            Some(&Position::Byte(0))
        );
    }

    /// A PNG assembled by hand (stored deflate blocks), for layouts our encoder never writes.
    fn handmade_png(
        w: u32,
        h: u32,
        depth: u8,
        color: u8,
        rows: &[u8],
        plte: Option<&[u8]>,
    ) -> Vec<u8> {
        fn crc32(bytes: &[u8]) -> u32 {
            let mut c = 0xFFFF_FFFFu32;
            for &b in bytes {
                c ^= b as u32;
                for _ in 0..8 {
                    c = if c & 1 != 0 {
                        0xEDB8_8320 ^ (c >> 1)
                    } else {
                        c >> 1
                    };
                }
            }
            !c
        }
        fn chunk(out: &mut Vec<u8>, kind: &[u8], data: &[u8]) {
            out.extend_from_slice(&(data.len() as u32).to_be_bytes());
            let mut body = kind.to_vec();
            body.extend_from_slice(data);
            out.extend_from_slice(&body);
            out.extend_from_slice(&crc32(&body).to_be_bytes());
        }
        let mut z = vec![0x78, 0x01, 0x01];
        z.extend_from_slice(&(rows.len() as u16).to_le_bytes());
        z.extend_from_slice(&(!(rows.len() as u16)).to_le_bytes());
        z.extend_from_slice(rows);
        let (mut a, mut b) = (1u32, 0u32);
        for &x in rows {
            a = (a + x as u32) % 65521;
            b = (b + a) % 65521;
        }
        z.extend_from_slice(&((b << 16) | a).to_be_bytes());
        let mut out = PNG_SIGNATURE.to_vec();
        let mut ihdr = Vec::new();
        ihdr.extend_from_slice(&w.to_be_bytes());
        ihdr.extend_from_slice(&h.to_be_bytes());
        ihdr.extend_from_slice(&[depth, color, 0, 0, 0]);
        chunk(&mut out, b"IHDR", &ihdr);
        if let Some(p) = plte {
            chunk(&mut out, b"PLTE", p);
        }
        chunk(&mut out, b"IDAT", &z);
        chunk(&mut out, b"IEND", &[]);
        out
    }

    #[test]
    fn one_bit_masks_and_palettes_expand() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.png");
        // 1-bit gray, 10 x 2: rows 1011001110 and all ones (filter byte 0 first).
        let rows = [0, 0b1011_0011, 0b1000_0000, 0, 0xFF, 0xC0];
        std::fs::write(&p, handmade_png(10, 2, 1, 0, &rows, None)).unwrap();
        let m = read_png(&p).unwrap();
        assert_eq!((m.width, m.height, m.channels), (10, 2, 1));
        let expect = [1., 0., 1., 1., 0., 0., 1., 1., 1., 0.];
        assert_eq!(&m.data[..10], &expect);
        assert!(m.data[10..].iter().all(|&v| v == 1.0));
        // 8-bit palette, 3 x 1, indices 2 0 1.
        let plte = [255, 0, 0, 0, 255, 0, 0, 0, 255];
        std::fs::write(&p, handmade_png(3, 1, 8, 3, &[0, 2, 0, 1], Some(&plte))).unwrap();
        let c = read_png(&p).unwrap();
        assert_eq!(c.channels, 3);
        assert_eq!(c.data, vec![0., 0., 1., 1., 0., 0., 0., 1., 0.]);
    }

    #[test]
    fn exr_half_float_channels_read_as_f32() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.exr");
        let vals: Vec<ex::f16> = (0..6)
            .map(|i| ex::f16::from_f32(i as f32 * 0.25 - 0.5))
            .collect();
        let layer = ex::Layer::new(
            (3, 2),
            ex::LayerAttributes::default(),
            ex::Encoding::default(),
            ex::AnyChannels::sort(ex::SmallVec::from_vec(vec![ex::AnyChannel::new(
                "Z",
                ex::FlatSamples::F16(vals),
            )])),
        );
        ex::Image::from_layer(layer).write().to_file(&p).unwrap();
        let img = read_exr(&p).unwrap();
        assert_eq!((img.width, img.height, img.channels), (3, 2, 1));
        assert_eq!(img.data, vec![-0.5, -0.25, 0.0, 0.25, 0.5, 0.75]);
    }

    #[test]
    fn bad_shapes_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.png");
        let mut img = pattern(2, 2, 3);
        img.data.pop();
        assert!(write_png(&p, &img).is_err());
        assert!(write_exr(dir.path().join("x.exr"), &img).is_err());
        let img5 = ImageF32 {
            width: 1,
            height: 1,
            channels: 5,
            data: vec![0.0; 5],
        };
        assert!(write_png(&p, &img5).is_err());
    }

    #[test]
    fn non_finite_samples_are_refused_by_both_writers() {
        let dir = tempfile::tempdir().unwrap();
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut img = pattern(3, 2, 1);
            img.data[4] = bad;
            for name in ["x.png", "x.exr"] {
                let p = dir.path().join(name);
                let e = write_image(&p, &img).unwrap_err().to_string();
                assert!(e.contains(name) && e.contains("index 4"), "{e}");
                assert!(!p.exists(), "{name} written despite {bad}");
            }
        }
    }
}
