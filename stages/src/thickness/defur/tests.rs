//! Analytic tests of the whole defurring on spheres.

use super::*;

/// An icosphere of radius `r` with `levels` subdivisions; vertices with
/// `z > cap_z * r` get part 1 ("eyes"), the rest part 0 ("torso").
pub(crate) fn icosphere(r: f32, levels: usize, cap_z: f32) -> Mesh {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut p: Vec<Vec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|a| Vec3::from_array(*a).normalize())
    .collect();
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut mid = std::collections::HashMap::new();
        let mut next = Vec::new();
        let mut m = |a: u32, b: u32, p: &mut Vec<Vec3>| -> u32 {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                p.push(((p[a as usize] + p[b as usize]) * 0.5).normalize());
                p.len() as u32 - 1
            })
        };
        for [a, b, c] in tris {
            let ab = m(a, b, &mut p);
            let bc = m(b, c, &mut p);
            let ca = m(c, a, &mut p);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        tris = next;
    }
    let part = p.iter().map(|v| u16::from(v.z > cap_z)).collect();
    let mut mesh = Mesh {
        positions: p.iter().map(|v| *v * r).collect(),
        normals: Vec::new(),
        triangles: tris,
        part,
        part_names: vec!["torso".into(), "eyes".into()],
    };
    mesh.recompute_normals();
    mesh
}

/// A shell on the outer sphere's vertices with widths `t` plus seeded noise.
fn shell_on(mesh: &Mesh, t: f32, noise: f32) -> ShellWidths {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    ShellWidths {
        positions: mesh.positions.clone(),
        normals: mesh.normals.clone(),
        widths: mesh
            .positions
            .iter()
            .map(|_| (t + noise * rng.gen_range(-1.0f32..1.0)).max(0.0))
            .collect(),
    }
}

#[test]
fn sphere_defurs_to_the_skin_radius() {
    // The smoothing length of the appendix's objective grows like the square
    // root of the edge length in scene units (sqrt(19 h) for unit data
    // weights), so use centimetre-like units where it is well below R.
    let (r, t) = (50.0f32, 5.0f32);
    let outer = icosphere(r + t, 3, 0.9);
    let shell = shell_on(&outer, t, 1.0);
    let prot = protected_parts(&outer.part_names, &protected_default());
    assert_eq!(prot, vec![false, true]);
    let res = defur(
        &outer,
        &shell,
        &prot,
        &BTreeMap::new(),
        &DefurSettings::default(),
    )
    .unwrap();
    assert!(res.solver.converged, "{:?}", res.solver);
    assert!(res.postcheck.clean, "{:?}", res.postcheck);
    let mut err = 0.0f32;
    let mut n = 0;
    for i in 0..outer.vertex_count() {
        // Bounds and protection.
        assert!(res.d[i] >= 0.0 && res.d[i] <= res.upper[i] + 1e-6);
        if res.protected[i] {
            assert_eq!(res.d[i], 0.0);
            assert_eq!(res.root.positions[i], outer.positions[i]);
        } else if outer.positions[i].z < 0.6 {
            // Away from the protected cap: the radius is the skin's.
            err += (res.root.positions[i].length() - r).abs();
            n += 1;
        }
    }
    let mean_err = err / n as f32;
    assert!(
        mean_err < 0.15 * t,
        "mean radius error {mean_err} for fur {t}"
    );
    // Topology and parts are kept.
    assert_eq!(res.root.triangles, outer.triangles);
    assert_eq!(res.root.part, outer.part);
}

#[test]
fn reference_thickness_pulls_the_part_guidance() {
    let outer = icosphere(1.1, 2, 2.0); // no protected cap
    let shell = shell_on(&outer, 0.1, 0.0);
    let prot = vec![false, false];
    let mut refs = BTreeMap::new();
    refs.insert("torso".to_string(), 0.0f32);
    let res = defur(&outer, &shell, &prot, &refs, &DefurSettings::default()).unwrap();
    let b = res.calibration[0].b;
    assert!((b - 0.065).abs() < 1e-4, "B = 0.65 W75 + 0.35 * 0 = {b}");
    // Supported everywhere at 0.1 and guided to 0.065: in between.
    let mean: f32 = res.d.iter().sum::<f32>() / res.d.len() as f32;
    assert!(mean > 0.065 && mean < 0.1, "{mean}");
}

#[test]
fn bounds_follow_opposing_surfaces() {
    // A thin fur on a small sphere: the inward ray hits the far side at 2R,
    // so u = min(0.45 * 2R, 0.05 D) with D = 2R sqrt(3).
    let outer = icosphere(0.5, 2, 2.0);
    let shell = shell_on(&outer, 0.3, 0.0);
    let res = defur(
        &outer,
        &shell,
        &[false, false],
        &BTreeMap::new(),
        &DefurSettings::default(),
    )
    .unwrap();
    let d_scale = outer.diagonal();
    for (i, &u) in res.upper.iter().enumerate() {
        let expect = (0.45f32 * 1.0).min(0.05 * d_scale);
        assert!(
            (u - expect).abs() < 0.02 * expect,
            "u[{i}] = {u}, expected {expect}"
        );
        assert!(res.d[i] <= u + 1e-6);
    }
    assert!(res.hit_fraction > 0.99);
}

#[test]
fn bad_inputs_are_errors() {
    let outer = icosphere(1.0, 1, 2.0);
    let mut shell = shell_on(&outer, 0.1, 0.0);
    shell.widths.pop();
    assert!(matches!(
        defur(
            &outer,
            &shell,
            &[false, false],
            &BTreeMap::new(),
            &DefurSettings::default()
        ),
        Err(DefurError::ShellArrays { .. })
    ));
    let mut shell = shell_on(&outer, 0.1, 0.0);
    shell.widths[3] = f32::NAN;
    assert!(matches!(
        defur(
            &outer,
            &shell,
            &[false, false],
            &BTreeMap::new(),
            &DefurSettings::default()
        ),
        Err(DefurError::ShellValue { index: 3, .. })
    ));
    let empty = Mesh::default();
    assert!(matches!(
        defur(
            &empty,
            &shell,
            &[],
            &BTreeMap::new(),
            &DefurSettings::default()
        ),
        Err(DefurError::EmptyMesh)
    ));
}

#[test]
fn weighted_percentiles() {
    let (m, p) = weighted_mean_p95(&[1.0, 2.0, 3.0], &[1.0, 1.0, 2.0], &[true, true, true]);
    assert!((m - 2.25).abs() < 1e-9);
    assert_eq!(p, 3.0);
    let (m, _) = weighted_mean_p95(&[1.0, 2.0, 3.0], &[1.0, 1.0, 2.0], &[true, true, false]);
    assert!((m - 1.5).abs() < 1e-9);
}

/// A furry sphere with locally varying widths (so that the smoothing strength matters), and the
/// same scaled by `k`: (small, its shell, big, its shell, k, fur thickness of the small one).
fn furry_sphere_at_two_scales() -> (Mesh, ShellWidths, Mesh, ShellWidths, f32, f32) {
    let (r, t) = (0.5f32, 0.05f32);
    let small = icosphere(r + t, 3, 0.9);
    let mut shell_small = shell_on(&small, t, 0.02);
    for (w, p) in shell_small.widths.iter_mut().zip(&small.positions) {
        *w *= 1.0 + 0.8 * (6.0 * p.x / (r + t)).sin();
    }
    let k = 100.0f32;
    let mut big = small.clone();
    for p in &mut big.positions {
        *p *= k;
    }
    let shell_big = ShellWidths {
        positions: shell_small.positions.iter().map(|p| *p * k).collect(),
        normals: shell_small.normals.clone(),
        widths: shell_small.widths.iter().map(|w| w * k).collect(),
    };
    (small, shell_small, big, shell_big, k, t)
}

#[test]
fn unit_scale_makes_the_solve_independent_of_the_scene_unit() {
    // The same furry sphere in two units (1 scene unit = 100 "cm" vs 1 cm):
    // with unit_scale = cm per scene unit the displacements agree (in cm);
    // read literally in scene units (unit_scale 1) they do not.
    let (small, shell_small, big, shell_big, k, t) = furry_sphere_at_two_scales();
    let prot = protected_parts(&small.part_names, &protected_default());
    let solve = |m: &Mesh, sh: &ShellWidths, unit: f64| {
        let s = DefurSettings {
            unit_scale: unit,
            ..Default::default()
        };
        defur(m, sh, &prot, &BTreeMap::new(), &s).unwrap().d_solved
    };
    let a = solve(&small, &shell_small, k as f64);
    let b = solve(&big, &shell_big, 1.0);
    let max_diff = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x * k - y).abs())
        .fold(0.0f32, f32::max);
    assert!(max_diff < 0.02 * t * k, "max difference {max_diff} cm");
    // The literal reading differs between the two units by much more.
    let c = solve(&small, &shell_small, 1.0);
    let lit_diff = c
        .iter()
        .zip(&b)
        .map(|(x, y)| (x * k - y).abs())
        .fold(0.0f32, f32::max);
    assert!(
        lit_diff > 10.0 * max_diff.max(1e-3),
        "literal {lit_diff} vs {max_diff}"
    );
}

#[test]
fn diagonal_units_make_the_solve_independent_of_the_scene_unit() {
    // The same furry sphere at two scales (x1 and x100): with the objective in units of the
    // bounding-box diagonal (unit_scale = 1 / D) the displacements agree up to the scale, with
    // no metric scale needed.
    let (small, shell_small, big, shell_big, k, t) = furry_sphere_at_two_scales();
    let prot = protected_parts(&small.part_names, &protected_default());
    let solve = |m: &Mesh, sh: &ShellWidths| {
        let s = DefurSettings {
            unit_scale: 1.0 / m.diagonal() as f64,
            ..Default::default()
        };
        defur(m, sh, &prot, &BTreeMap::new(), &s).unwrap().d_solved
    };
    let (a, b) = (solve(&small, &shell_small), solve(&big, &shell_big));
    let max_diff = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x * k - y).abs())
        .fold(0.0f32, f32::max);
    assert!(max_diff < 0.02 * t * k, "max difference {max_diff}");
    assert!(a.iter().any(|&d| d > 0.1 * t), "nothing was defurred");
}
