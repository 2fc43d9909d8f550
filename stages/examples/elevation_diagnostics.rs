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
use fure_stages::maths::geom::{MeshQuery, PointIndex};
use glam::{Mat3, Vec2, Vec3};

use common::{OrientationRun, Res};

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

/// The unit eigenvector of a symmetric 3x3 matrix with the least eigenvalue (power iteration
/// on `trace I - m`, whose largest eigenvalue is `m`'s least).
fn least_eigenvector(m: Mat3) -> Vec3 {
    let shift = Mat3::from_diagonal(Vec3::splat(m.x_axis.x + m.y_axis.y + m.z_axis.z)) - m;
    let mut v = Vec3::new(0.3, 0.5, 0.8).normalize();
    for _ in 0..100 {
        v = (shift * v).try_normalize().unwrap_or(Vec3::Z);
    }
    v
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
    let lift = 1e-3 * outer.diagonal();

    // Per root: the envelope point, its normal, and the summed plane-normal tensor.
    let n = roots.len();
    let mut point = vec![Vec3::ZERO; n];
    let mut normal = vec![Vec3::ZERO; n];
    let mut tensor = vec![Mat3::ZERO; n];
    for i in 0..n {
        let (q, _, tri) = query.closest_point(roots.positions[i]);
        let [a, b, c] = outer.triangles[tri as usize].map(|k| outer.positions[k as usize]);
        let nq = (b - a).cross(c - a).normalize_or_zero();
        point[i] = q;
        normal[i] = nq;
        for (cam, (angle, conf)) in cams.iter().zip(&maps) {
            let to_cam = cam.center() - q;
            let dist = to_cam.length();
            let facing = nq.dot(to_cam / dist);
            if facing < 0.2 {
                continue;
            }
            let (px, depth) = cam.project(q);
            if depth.is_nan() || depth <= 0.0 || px.x < 0.0 || px.y < 0.0 {
                continue;
            }
            let (x, y) = (px.x as u32, px.y as u32);
            if x >= cam.width || y >= cam.height {
                continue;
            }
            let k = (y * cam.width + x) as usize;
            let (alpha, c) = (angle.data[k], conf.data[k]);
            if c.is_nan() || c <= 0.0 || !alpha.is_finite() {
                continue;
            }
            if query
                .ray_hit(q + nq * lift, to_cam / dist, dist - lift)
                .is_some()
            {
                continue;
            }
            let u = Vec2::new(alpha.cos(), alpha.sin());
            let (_, r1) = cam.ray(px.x, px.y);
            let (_, r2) = cam.ray(px.x + u.x, px.y + u.y);
            let Some(pn) = r1.cross(r2).try_normalize() else {
                continue;
            };
            let w = c * facing;
            tensor[i] += Mat3::from_cols(pn * pn.x, pn * pn.y, pn * pn.z) * w;
        }
    }
    // Pooling over neighbours, and the elevation of the pooled direction.
    let index = PointIndex::new(&roots.positions)?;
    let gt_roots: Vec<Vec3> = (0..gt.len()).map(|s| gt.strand(s)[0]).collect();
    let gt_index = PointIndex::new(&gt_roots)?;
    let elevation = |d: Vec3, nq: Vec3| d.dot(nq).abs().clamp(0.0, 1.0).asin().to_degrees();
    let codec = read_hair(dir.join("codec/strands.hair")).ok();
    let (mut est, mut truth, mut learned) = (Vec::new(), Vec::new(), Vec::new());
    for i in (0..n).step_by((n / 4000).max(1)) {
        let mut m = Mat3::ZERO;
        for (j, _) in index.within(roots.positions[i], radius_px * footprint) {
            m += tensor[j];
        }
        if m.x_axis.x + m.y_axis.y + m.z_axis.z <= 0.0 {
            continue;
        }
        est.push(elevation(least_eigenvector(m), normal[i]));
        let g = gt.strand(gt_index.nearest(roots.positions[i]).0);
        let chord = g[((g.len() - 1) / 3).max(1)] - g[0];
        truth.push(elevation(chord.normalize_or_zero(), normal[i]));
        if let Some(c) = codec.as_ref().filter(|c| c.len() == n) {
            let s = c.strand(i);
            let chord = s[((s.len() - 1) / 3).max(1)] - s[0];
            learned.push(elevation(chord.normalize_or_zero(), normal[i]));
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
    println!(
        "roots sampled {}, pooling {radius_px} px: elevation from the views median {:.1} deg, GT {:.1} deg, codec {}; per-root Pearson {corr:.2}",
        est.len(),
        median(est.clone()),
        median(truth.clone()),
        if learned.is_empty() {
            "-".to_string()
        } else {
            format!("{:.1} deg", median(learned))
        }
    );
    Ok(())
}
