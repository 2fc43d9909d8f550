//! How well the fur's axis lifted from the views ([`fure_stages::growth::view_axes`]) follows
//! the ground-truth strands, against the roots' own frames. Needs a synthetic scene (its GT strands)
//! and a run through `orientation`.
//!
//! ```sh
//! fure run pipelines/tiger.toml --until orientation
//! cargo run -p fure-stages --release --example view_axes_diagnostics -- out/tiger [radius_px ...]
//! ```
//!
//! Per pooling radius (in pixel footprints; default 0 1 2 4): the in-plane direction error
//! (`evaluate`'s `direction_error_deg`, growth sign counted) of straight strands along the roots'
//! tangents, along the tangents turned onto the view axes, and the same from tangents first turned 45
//! degrees (the wrong-start test's start), each for all roots and for the roots whose coherence is at
//! least 0.3.

mod common;

use std::path::Path;

use fure_stages::data::camera::pixel_footprint;
use fure_stages::data::mesh::Mesh;
use fure_stages::data::strands::Strands;
use fure_stages::evaluation::evaluate::direction_error_deg;
use fure_stages::formats::obj::read_obj;
use fure_stages::growth::view_axes::{view_axes, ViewOrientation};
use glam::Mat3;

use common::{OrientationRun, Res};

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

fn run() -> Res<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dir = Path::new(
        args.first()
            .ok_or("usage: view_axes_diagnostics OUT_DIR [radius_px ...]")?,
    );
    let radii: Vec<f32> = if args.len() > 1 {
        args[1..]
            .iter()
            .map(|a| a.parse())
            .collect::<Result<_, _>>()?
    } else {
        vec![0.0, 1.0, 2.0, 4.0]
    };
    let OrientationRun {
        roots,
        outer,
        cameras: cams,
        maps,
        gt,
    } = OrientationRun::load(dir)?;
    let views = ViewOrientation::pair(&cams, &maps);
    let skin: Mesh = read_obj(dir.join("scene/skin.obj"))?;
    let footprint = pixel_footprint(&cams, &outer);
    println!(
        "roots {}, views {}, pixel footprint {footprint:.4} scene units",
        roots.len(),
        cams.len()
    );

    let frames: Vec<Mat3> = (0..roots.len())
        .map(|i| Mat3::from_cols(roots.tangents[i], roots.bitangents[i], roots.normals[i]))
        .collect();
    let turned: Vec<Mat3> = frames
        .iter()
        .map(|f| *f * Mat3::from_rotation_z(45f32.to_radians()))
        .collect();
    let strands = |frames: &[Mat3], keep: &dyn Fn(usize) -> bool| -> Strands {
        let mut s = Strands::new();
        for (i, f) in frames.iter().enumerate() {
            if keep(i) {
                let p = roots.positions[i];
                s.push(
                    &[p, p + f.x_axis * roots.length[i].max(1e-6)],
                    0,
                    0.0,
                    [0.5; 3],
                );
            }
        }
        s
    };
    let err = |s: &Strands| -> Res<String> {
        Ok(direction_error_deg(s, &gt, Some(&skin))?.map_or("-".into(), |d| format!("{d:.1}")))
    };
    let all = |_: usize| true;
    println!(
        "roots' frames: {} deg; turned 45: {} deg",
        err(&strands(&frames, &all))?,
        err(&strands(&turned, &all))?
    );
    println!("| radius (px) | min coherence | turned share | from the frames | from 45 deg |");
    println!("|---|---|---|---|---|");
    for r in radii {
        let from_frames = view_axes(
            &roots.positions,
            &frames,
            &outer,
            &views,
            r * footprint,
            None,
        )?;
        let from_turned = view_axes(
            &roots.positions,
            &turned,
            &outer,
            &views,
            r * footprint,
            None,
        )?;
        for c_min in [0.0f32, 0.2, 0.4, 0.6] {
            let snap =
                |start: &[Mat3], axes: &[fure_stages::growth::view_axes::ViewAxis]| -> Vec<Mat3> {
                    start
                        .iter()
                        .zip(axes)
                        .map(|(f, a)| {
                            if a.coherence >= c_min {
                                *f * Mat3::from_rotation_z(a.turn)
                            } else {
                                *f
                            }
                        })
                        .collect()
                };
            let share = from_frames.iter().filter(|a| a.coherence >= c_min).count() as f32
                / roots.len() as f32;
            println!(
                "| {r} | {c_min} | {share:.2} | {} | {} |",
                err(&strands(&snap(&frames, &from_frames), &all))?,
                err(&strands(&snap(&turned, &from_turned), &all))?
            );
        }
    }
    Ok(())
}
