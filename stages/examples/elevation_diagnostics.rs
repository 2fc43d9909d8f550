//! Can the views tell how steeply the fur rises? Each view's Gabor line at a root's envelope
//! point, with the camera centre, spans a plane that holds the strand's 3D direction; the
//! direction the views agree on is the one closest to lying in all those planes (the least
//! eigenvector of the summed plane normals' outer products, pooled over the roots within a few
//! pixel footprints). Its elevation above the envelope's tangent plane is compared with the GT
//! strands' (first third of the nearest GT strand), and with the elevation of the codec's
//! strands when the run has them. Needs a synthetic scene (its GT strands) and a run through
//! `orientation` (and `codec` for the last column).
//!
//! ```sh
//! cargo run -p fure-stages --release --example elevation_diagnostics -- out/tiger [radius_px]
//! ```

mod common;

use fure_stages::data::camera::pixel_footprint;
use fure_stages::formats::hair::read_hair;
use fure_stages::growth::view_axes::{view_elevations, PlaneTensors, ViewOrientation};
use fure_stages::maths::geom::{MeshQuery, PointIndex};
use glam::Vec3;

use common::{OrientationRun, Res};

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(f32::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f32::NAN)
}

fn run() -> Res<()> {
    let (dir, args) = common::out_dir_and_args("elevation_diagnostics OUT_DIR [radius_px]")?;
    let radius_px: f32 = args.first().map_or(Ok(4.0), |a| a.parse())?;
    let run = OrientationRun::load(&dir)?;
    let (roots, outer, cams, maps, gt) = (run.roots, run.outer, run.cameras, run.maps, run.gt);
    let footprint = pixel_footprint(&cams, &outer);
    let query = MeshQuery::new(&outer)?;
    let views = ViewOrientation::pair(&cams, &maps);
    let n = roots.len();
    let sampled = view_elevations(
        &roots.positions,
        &outer,
        &views,
        radius_px * footprint,
        (n / 4000).max(1),
    )?;
    let gt_roots: Vec<Vec3> = (0..gt.len()).map(|s| gt.strand(s)[0]).collect();
    let gt_index = PointIndex::new(&gt_roots)?;
    let elevation = |d: Vec3, nq: Vec3| d.dot(nq).abs().clamp(0.0, 1.0).asin().to_degrees();
    let codec = read_hair(dir.join("codec/strands.hair")).ok();
    let (mut est, mut truth, mut learned) = (Vec::new(), Vec::new(), Vec::new());
    let mut part_of = Vec::new();
    for reading in sampled {
        let i = reading.root;
        part_of.push(roots.part[i] as usize);
        // The envelope's normal at the root's closest point, as view_elevations measures.
        let (_, _, tri) = query.closest_point(roots.positions[i]);
        let [a, b, c] = outer.triangles[tri as usize].map(|k| outer.positions[k as usize]);
        let nq = (b - a).cross(c - a).normalize_or_zero();
        est.push(reading.elevation.to_degrees());
        let g = gt.strand(gt_index.nearest(roots.positions[i]).0);
        let chord = g[((g.len() - 1) / 3).max(1)] - g[0];
        truth.push(elevation(chord.normalize_or_zero(), nq));
        if let Some(c) = codec.as_ref().filter(|c| c.len() == n) {
            let s = c.strand(i);
            let chord = s[((s.len() - 1) / 3).max(1)] - s[0];
            learned.push(elevation(chord.normalize_or_zero(), nq));
        }
    }
    let corr = {
        let (me, mt) = (
            est.iter().sum::<f32>() / est.len() as f32,
            truth.iter().sum::<f32>() / truth.len() as f32,
        );
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for (a, b) in est.iter().zip(&truth) {
            sab += (a - me) * (b - mt);
            saa += (a - me) * (a - me);
            sbb += (b - mt) * (b - mt);
        }
        sab / (saa * sbb).sqrt()
    };
    // The same reading from maps that carry no direction (every pixel's angle drawn uniformly,
    // the confidence kept): what the estimator returns when the views say nothing.
    let random_maps: Vec<_> = maps
        .iter()
        .enumerate()
        .map(|(v, (angle, conf))| {
            let mut a = angle.clone();
            for (k, x) in a.data.iter_mut().enumerate() {
                let h = (k as u64 ^ ((v as u64) << 32)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                let h = (h ^ (h >> 29)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                *x = ((h >> 11) as f64 / (1u64 << 53) as f64 * std::f64::consts::PI) as f32;
            }
            (a, conf.clone())
        })
        .collect();
    let null = PlaneTensors::with_null(
        &roots.positions,
        &outer,
        &ViewOrientation::pair(&cams, &random_maps),
    )?
    .elevations(radius_px * footprint, (n / 4000).max(1));
    println!(
        "random maps: elevation median {:.1} deg; the readings' null (view_axes::PlaneTensors) {:.1} deg",
        median(null.iter().map(|r| r.elevation.to_degrees()).collect()),
        median(null.iter().filter_map(|r| r.null_elevation).map(f32::to_degrees).collect())
    );
    println!(
        "roots sampled {}, pooling {radius_px} px: elevation from the views median {:.1} deg, GT {:.1} deg, codec {}; per-root Pearson {corr:.2}",
        est.len(),
        median(est.clone()),
        median(truth.clone()),
        if learned.is_empty() {
            "-".to_string()
        } else {
            format!("{:.1} deg", median(learned.clone()))
        }
    );
    // Per part: do the views tell a steep part from a flat one?
    for (p, name) in roots.part_names.iter().enumerate() {
        let pick = |v: &[f32]| -> Vec<f32> {
            v.iter()
                .zip(&part_of)
                .filter(|&(_, &q)| q == p)
                .map(|(x, _)| *x)
                .collect()
        };
        let (e, t) = (pick(&est), pick(&truth));
        if e.len() < 20 {
            continue;
        }
        let c = if learned.len() == est.len() {
            format!("{:.1}", median(pick(&learned)))
        } else {
            "-".into()
        };
        println!(
            "  {name:<12} roots {:>5}: views {:.1} deg, GT {:.1} deg, codec {c}",
            e.len(),
            median(e),
            median(t)
        );
    }
    Ok(())
}
