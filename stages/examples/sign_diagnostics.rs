//! Can the views tell which way the fur grows? The line the views agree on at a root
//! (`view_elevations`) rises off the envelope; pointed away from it, its tangential part says
//! which way along the line the fur leaves the skin. Compared per part with the GT strands'
//! growth (first third of the nearest GT strand, projected on the tangent plane) and with the
//! roots' prior sign. Needs a synthetic scene (its GT strands) and a run through `orientation`.
//!
//! ```sh
//! cargo run -p fure-stages --release --example sign_diagnostics -- out/tiger [radius_px] [min_elevation_deg]
//! ```

mod common;

use fure_stages::data::camera::pixel_footprint;
use fure_stages::growth::view_axes::{view_elevations, ViewOrientation};
use fure_stages::maths::geom::{MeshQuery, PointIndex};
use glam::Vec3;

use common::{OrientationRun, Res};

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

#[derive(Default, Clone)]
struct Tally {
    roots: usize,
    views_right: f64,
    views_weight: f64,
    prior_right: usize,
    // Sum of w * sign(line . T): the views' vote on the prior's sign.
    vote: f64,
    // Sum of w * sign(line . gt).
    vote_gt: f64,
}

fn run() -> Res<()> {
    let (dir, args) =
        common::out_dir_and_args("sign_diagnostics OUT_DIR [radius_px] [min_elevation_deg]")?;
    let radius_px: f32 = args.first().map_or(Ok(16.0), |a| a.parse())?;
    let min_elev: f32 = args.get(1).map_or(Ok(10.0), |a| a.parse())?;
    let run = OrientationRun::load(&dir)?;
    let (roots, outer, cams, maps, gt) = (run.roots, run.outer, run.cameras, run.maps, run.gt);
    let footprint = pixel_footprint(&cams, &outer);
    let query = MeshQuery::new(&outer)?;
    let views = ViewOrientation::pair(&cams, &maps);
    let n = roots.positions.len();
    let sampled = view_elevations(
        &roots.positions,
        &outer,
        &views,
        radius_px * footprint,
        (n / 8000).max(1),
    )?;
    let gt_roots: Vec<Vec3> = (0..gt.len()).map(|s| gt.strand(s)[0]).collect();
    let gt_index = PointIndex::new(&gt_roots)?;
    let mut tally = vec![Tally::default(); roots.part_names.len()];
    for r in sampled {
        if r.spread < 0.05 || r.elevation.to_degrees() < min_elev {
            continue;
        }
        let i = r.root;
        let (_, _, tri) = query.closest_point(roots.positions[i]);
        let [a, b, c] = outer.triangles[tri as usize].map(|k| outer.positions[k as usize]);
        let nq = (b - a).cross(c - a).normalize_or_zero();
        let tangential = |d: Vec3| (d - nq * d.dot(nq)).normalize_or_zero();
        let g = gt.strand(gt_index.nearest(roots.positions[i]).0);
        let gt_dir = tangential(g[((g.len() - 1) / 3).max(1)] - g[0]);
        let line = tangential(r.line);
        let t = tangential(roots.tangents[i]);
        if gt_dir == Vec3::ZERO || line == Vec3::ZERO {
            continue;
        }
        // Sign is weak where the line lies flat or stands up.
        let w = (2.0 * r.elevation).sin() as f64;
        let x = &mut tally[roots.part[i] as usize];
        x.roots += 1;
        x.views_weight += w;
        if line.dot(gt_dir) > 0.0 {
            x.views_right += w;
        }
        if t.dot(gt_dir) > 0.0 {
            x.prior_right += 1;
        }
        x.vote += w * (line.dot(t)).signum() as f64;
        x.vote_gt += w * (line.dot(gt_dir)).signum() as f64;
    }
    println!("radius {radius_px} px, lines rising at least {min_elev} deg");
    println!("part          roots  views right (weighted)  prior right  views' vote on prior  vote on GT");
    let mut all = Tally::default();
    for (p, x) in tally.iter().enumerate() {
        if x.roots < 10 {
            continue;
        }
        println!(
            "{:<12} {:>6}  {:>10.1} %  {:>12.1} %  {:>+10.2}  {:>+10.2}",
            roots.part_names[p],
            x.roots,
            100.0 * x.views_right / x.views_weight,
            100.0 * x.prior_right as f64 / x.roots as f64,
            x.vote / x.views_weight,
            x.vote_gt / x.views_weight,
        );
        all.roots += x.roots;
        all.views_right += x.views_right;
        all.views_weight += x.views_weight;
        all.prior_right += x.prior_right;
    }
    println!(
        "all          {:>6}  {:>10.1} %  {:>12.1} %",
        all.roots,
        100.0 * all.views_right / all.views_weight,
        100.0 * all.prior_right as f64 / all.roots as f64
    );
    Ok(())
}
