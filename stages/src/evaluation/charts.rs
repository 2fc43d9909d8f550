//! Chart output shared by the reports (speed against accuracy, the benchmark suite, stability).
//!
//! `plotters` draws every chart; the PNG goes through its bitmap backend into an RGB buffer that
//! `formats::images::write_png` encodes (no system libraries), with text from the DejaVu Sans font
//! bundled in `stages/assets` (Bitstream Vera licence, `DejaVuSans.LICENSE`) through `ab_glyph`, so no
//! fontconfig is needed; the SVG is written by its SVG backend (text as SVG text elements, family
//! `sans-serif`).

use std::path::Path;
use std::sync::Once;

use fure_stage_api::StageError;
use plotters::coord::Shift;
use plotters::prelude::*;

/// The bundled font (DejaVu Sans, Bitstream Vera licence).
static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
static FONT_ONCE: Once = Once::new();

fn register_font() {
    FONT_ONCE.call_once(|| {
        // The bundled file is a valid TTF; if it could not be parsed text would be missing, which the
        // chart drawing then reports as an error.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// Axis numbers without a needless ".0" (0.01, 0.5, 10, 2500).
pub fn fmt_num(x: f64) -> String {
    if x >= 1.0 {
        format!("{x:.0}")
    } else {
        let s = format!("{x:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

pub fn chart_err<E: std::fmt::Debug>(e: E) -> String {
    format!("chart drawing failed: {e:?}")
}

/// Renders a chart to PNG bytes on disk through an RGB buffer.
pub fn write_png_chart(
    path: &Path,
    size: (u32, u32),
    draw: impl Fn(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), String>,
) -> Result<(), StageError> {
    register_font();
    let mut buf = vec![0u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        draw(&root).map_err(|e| StageError::failed(format!("{}: {e}", path.display())))?;
    }
    let img = crate::data::image::ImageF32 {
        width: size.0,
        height: size.1,
        channels: 3,
        data: buf.iter().map(|v| *v as f32 / 255.0).collect(),
    };
    crate::formats::images::write_png(path, &img)?;
    Ok(())
}

/// Renders a chart to an SVG file.
pub fn write_svg_chart(
    path: &Path,
    size: (u32, u32),
    draw: impl Fn(&DrawingArea<SVGBackend<'_>, Shift>) -> Result<(), String>,
) -> Result<(), StageError> {
    register_font();
    let mut s = String::new();
    {
        let root = SVGBackend::with_string(&mut s, size).into_drawing_area();
        draw(&root).map_err(|e| StageError::failed(format!("{}: {e}", path.display())))?;
    }
    std::fs::write(path, s).map_err(|e| StageError::io(path, e))
}
