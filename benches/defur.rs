//! Benchmark of the defurring solve (`cargo bench --bench defur`).
//!
//! The mesh is a closed torus (major radius 1, minor radius 0.35) of
//! 200 x 100 = 20,000 vertices with four parts (two fur parts, a third fur
//! part, and a protected "eyes" band), outward normals, and a Frosting-like
//! shell on its vertices whose widths vary smoothly (0.01 to 0.05 scene
//! units) with 10% seeded noise. The bench runs the whole `defur` library
//! call once (cues, bounds, solve, post-check) and reports its solve time,
//! then times the bounded solve alone (same problem) several times and
//! prints the median. Target (issue 5): solve <= 2 s on a 2-core machine,
//! release build. Figures are also written as JSON to
//! `target/bench/defur.json`.
//!
//! Environment: `RAYON_NUM_THREADS` sets the thread count (the solve itself
//! is single-threaded).

use std::collections::BTreeMap;
use std::time::Instant;

use fure_stages::data::mesh::Mesh;
use fure_stages::data::shell::ShellWidths;
use fure_stages::render::Vec3;
use fure_stages::thickness::defur::{defur, DefurSettings};

mod common;
use common::Rng;

fn torus(nu: usize, nv: usize) -> Mesh {
    let (big, small) = (1.0f32, 0.35f32);
    let tau = std::f32::consts::TAU;
    let mut positions = Vec::with_capacity(nu * nv);
    let mut normals = Vec::with_capacity(nu * nv);
    let mut part = Vec::with_capacity(nu * nv);
    for i in 0..nu {
        let u = tau * i as f32 / nu as f32;
        for j in 0..nv {
            let v = tau * j as f32 / nv as f32;
            let centre = Vec3::new(big * u.cos(), big * u.sin(), 0.0);
            let n = Vec3::new(v.cos() * u.cos(), v.cos() * u.sin(), v.sin());
            positions.push(centre + small * n);
            normals.push(n);
            let p = if i < nu / 40 {
                3 // a thin protected band
            } else {
                (i * 3 / nu) as u16
            };
            part.push(p);
        }
    }
    let id = |i: usize, j: usize| ((i % nu) * nv + (j % nv)) as u32;
    let mut triangles = Vec::with_capacity(2 * nu * nv);
    for i in 0..nu {
        for j in 0..nv {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    Mesh {
        positions,
        normals,
        triangles,
        part,
        part_names: vec!["torso".into(), "belly".into(), "tail".into(), "eyes".into()],
    }
}

fn main() {
    let mesh = torus(200, 100);
    let mut rng = Rng(7);
    let widths: Vec<f32> = mesh
        .positions
        .iter()
        .map(|p| {
            let base = 0.03 + 0.02 * (3.0 * p.x).sin() * (2.0 * p.y).cos();
            base * (1.0 + 0.1 * (2.0 * rng.next() - 1.0))
        })
        .collect();
    let shell = ShellWidths {
        positions: mesh.positions.clone(),
        normals: mesh.normals.clone(),
        widths,
    };
    let protected = [false, false, false, true];
    let settings = DefurSettings::default();

    let t0 = Instant::now();
    let res = defur(&mesh, &shell, &protected, &BTreeMap::new(), &settings).expect("defur");
    let total = t0.elapsed().as_secs_f64();
    println!(
        "defur on {} vertices / {} triangles: total {:.3} s, solve {:.3} s ({} iterations, {}), post-check clean = {} ({} vertices reduced)",
        mesh.positions.len(),
        mesh.triangles.len(),
        total,
        res.seconds_solve,
        res.solver.iterations,
        res.solver.termination,
        res.postcheck.clean,
        res.postcheck.vertices_reduced
    );

    // The solve alone, repeated (the library call above re-solves the same problem each time).
    let mut times = Vec::new();
    let mut iterations = 0;
    for _ in 0..3 {
        let r = defur(&mesh, &shell, &protected, &BTreeMap::new(), &settings).expect("defur");
        times.push(r.seconds_solve);
        iterations = r.solver.iterations;
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    let unpre = DefurSettings {
        precondition: false,
        ..DefurSettings::default()
    };
    let r = defur(&mesh, &shell, &protected, &BTreeMap::new(), &unpre).expect("defur");
    println!(
        "solve median of 3: {median:.3} s ({iterations} iterations); without preconditioning: {:.3} s ({} iterations, {}); target <= 2 s",
        r.seconds_solve, r.solver.iterations, r.solver.termination
    );
    let record = format!(
        "{{\"vertices\": {}, \"solve_median_s\": {median}, \"iterations\": {iterations}, \"total_s\": {total}, \"unpreconditioned_solve_s\": {}, \"unpreconditioned_iterations\": {}}}\n",
        mesh.positions.len(),
        r.seconds_solve,
        r.solver.iterations
    );
    let _ = std::fs::create_dir_all("target/bench");
    let _ = std::fs::write("target/bench/defur.json", record);
}
