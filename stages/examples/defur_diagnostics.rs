//! Defurring diagnostics on a pipeline run's outputs: how far M_outer, M_root and
//! the alternatives lie from the ground-truth skin, to separate the defurring's own
//! error from the Frosting cue's. Needs a synthetic scene (its ground truth).
//!
//! ```sh
//! fure run pipelines/tiger.toml            # or any pipeline with the same stage names
//! cargo run -p fure-stages --release --example defur_diagnostics -- out/tiger [oracle|diagnose]
//! ```
//!
//! - `oracle`: the error budget with *oracle* widths, the true per-vertex
//!   outer-to-skin distances. Prints, as fractions of the mean GT fur thickness:
//!   displacing each vertex directly by its oracle width (closest-point distance,
//!   and the ray distance along `-n`), then the same widths through the appendix
//!   solve in scene units (the literal reading), in centimetres (`units = "cm"`),
//!   with `eta = 0` and with `lambda = 0`; then the lengths the oracle widths would
//!   give with the default multipliers (`T_p = s_cm P75(oracle)`), and the
//!   multiplier each part would need (`GT mean length / T_p`). Reads
//!   `parts/mesh.obj`, `scene/skin.obj`, `scene/scene.json`.
//! - `diagnose`: where the defurring error of the run comes from, per part and per
//!   step: outer-to-skin, ray, raw Frosting width and root-to-skin distances per
//!   part, the error of displacing by each candidate reading (oracle, widths, GT
//!   thicknesses, the hull-to-fur gap, the `offsets` crossings), their Pearson
//!   correlation with the true distance, and each through the solve in scene units
//!   and centimetres. Also reads `frosting/shell.json`, `defur/root_mesh.obj` and,
//!   when present, `scene/strands.hair` and `frosting/offsets.json`.
//!
//! Without a mode both run. The figures measured with it are in docs/history.md.

mod common;

use std::collections::BTreeMap;
use std::error::Error;
use std::path::{Path, PathBuf};

use fure_stages::data::mesh::Mesh;
use fure_stages::data::scene::SceneInfo;
use fure_stages::data::shell::ShellWidths;
use fure_stages::data::strands::Strands;
use fure_stages::formats::hair::read_hair;
use fure_stages::formats::json::read_json;
use fure_stages::formats::obj::read_obj;
use fure_stages::maths::geom::{MeshQuery, PointIndex};
use fure_stages::maths::stats::percentile;
use fure_stages::surface::parts::protected_parts;
use fure_stages::thickness::defur::{
    defur, distances_to, gt_mean_thickness_cm, postcheck, thickness, vertex_areas, vertex_normals,
    DefurSettings, GtComparison, DEFAULT_PROTECTED,
};
use fure_stages::thickness::frosting::Offsets;

type Res = Result<(), Box<dyn Error>>;

/// What both diagnostics read: M_outer with its parts, the GT skin and scene.
struct Loaded {
    dir: PathBuf,
    outer: Mesh,
    scene: SceneInfo,
    normals: Vec<glam::Vec3>,
    prot: Vec<bool>,
    gt: GtComparison,
}

fn load(dir: &Path) -> Result<Loaded, Box<dyn Error>> {
    let outer = read_obj(dir.join("parts/mesh.obj"))?;
    let skin_mesh = read_obj(dir.join("scene/skin.obj"))?;
    let scene: SceneInfo = read_json(dir.join("scene/scene.json"))?;
    if !scene.s_cm.is_some_and(|s| s > 0.0 && s.is_finite()) {
        return Err(
            "scene/scene.json: field `s_cm` (the synthetic scene's centimetres per unit) \
                    is missing or not positive: the diagnostics read a synthetic run"
                .into(),
        );
    }
    let normals = vertex_normals(&outer);
    let protected: Vec<String> = DEFAULT_PROTECTED.iter().map(|s| s.to_string()).collect();
    let prot = protected_parts(&outer.part_names, &protected);
    let thickness_cm = gt_mean_thickness_cm(&skin_mesh, &scene)
        .ok_or("scene.json has no mean_thickness_cm for a fur part of the GT skin")?;
    let gt = GtComparison {
        skin: MeshQuery::new(&skin_mesh)?,
        s_cm: f64::from(scale(&scene)),
        thickness_cm,
        thickness_source: "scene",
    };
    Ok(Loaded {
        dir: dir.to_path_buf(),
        outer,
        scene,
        normals,
        prot,
        gt,
    })
}

/// The synthetic scene's centimetres per unit (`load` refuses a scene without it).
fn scale(scene: &SceneInfo) -> f32 {
    scene.s_cm.expect("load checks the scene's s_cm")
}

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

fn run() -> Res {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (dir, mode) = match args.as_slice() {
        [dir] => (dir, "all"),
        [dir, mode] if ["oracle", "diagnose", "all"].contains(&mode.as_str()) => {
            (dir, mode.as_str())
        }
        _ => {
            return Err("usage: defur_diagnostics OUT_DIR/PIPELINE [oracle|diagnose|all]".into());
        }
    };
    let dir = Path::new(dir);
    if mode != "diagnose" {
        eprintln!("== oracle: the error budget with oracle widths");
        oracle(load(dir)?)?;
    }
    if mode != "oracle" {
        eprintln!("== diagnose: where the defurring error comes from");
        diagnose(load(dir)?)?;
    }
    Ok(())
}

/// The error budget with oracle widths (see the file's doc).
fn oracle(run: Loaded) -> Res {
    let Loaded {
        outer,
        scene,
        normals,
        prot,
        gt,
        ..
    } = run;
    let closest = distances_to(&gt.skin, &outer);
    let ray: Vec<f32> = outer
        .positions
        .iter()
        .zip(&normals)
        .zip(&closest)
        .map(|((&p, &n), &c)| gt.skin.ray_hit(p, -n, 1.0).unwrap_or(c))
        .collect();
    let o = gt.measure(&outer, &prot);
    eprintln!(
        "GT fur thickness {:.3} cm; M_outer -> skin {:.3} cm ({:.1}%)",
        gt.thickness_cm,
        o.mean_cm,
        100.0 * o.mean_frac
    );
    let variants = [
        ("scene units (literal)", DefurSettings::default()),
        (
            "units = cm",
            DefurSettings {
                unit_scale: f64::from(scale(&scene)),
                ..DefurSettings::default()
            },
        ),
        (
            "eta = 0",
            DefurSettings {
                eta: 0.0,
                ..DefurSettings::default()
            },
        ),
        (
            "lambda = 0",
            DefurSettings {
                lambda: 0.0,
                ..DefurSettings::default()
            },
        ),
    ];
    for (name, w) in [("closest", &closest), ("ray along -n", &ray)] {
        let d: Vec<f32> = w
            .iter()
            .zip(&outer.part)
            .map(|(&x, &p)| if prot[p as usize] { 0.0 } else { x })
            .collect();
        let mut m = outer.clone();
        m.positions = postcheck::displace(&outer.positions, &normals, &d);
        let r = gt.measure(&m, &prot);
        eprintln!(
            "oracle {name}: direct displacement {:.1}%",
            100.0 * r.mean_frac
        );
        let shell = ShellWidths {
            positions: outer.positions.clone(),
            normals: normals.clone(),
            widths: w.clone(),
        };
        for (label, s) in &variants {
            let res = defur(&outer, &shell, &prot, &BTreeMap::new(), s)?;
            let r = gt.measure(&res.root, &prot);
            eprintln!(
                "  solve, {label:22} {:.1}% (p95 {:.3} cm, post-check reduced {} vertices)",
                100.0 * r.mean_frac,
                r.p95_cm,
                res.postcheck.vertices_reduced
            );
        }
    }
    eprintln!("part          GT_len  T_p(oracle)  m_p  oracle_len  err%   needed m_p");
    let defaults: BTreeMap<&str, f32> = fure_stages::thickness::lengths::DEFAULT_MULTIPLIERS
        .iter()
        .copied()
        .collect();
    for (pi, name) in outer.part_names.iter().enumerate() {
        let Some(info) = scene.parts.get(name) else {
            continue;
        };
        let gt_len = info.mean_length_cm.unwrap_or(0.0);
        if prot[pi] || !info.fur || gt_len <= 0.0 {
            continue;
        }
        let v: Vec<f32> = (0..outer.positions.len())
            .filter(|&i| outer.part[i] as usize == pi)
            .map(|i| closest[i])
            .collect();
        let t_cm = scale(&scene) * percentile(&v, 75.0).unwrap_or(0.0);
        let m = defaults.get(name.as_str()).copied().unwrap_or(2.5);
        let l = m * t_cm;
        eprintln!(
            "{name:12} {gt_len:7.2} {t_cm:10.2} {m:6.2} {l:9.2} {:7.1} {:9.2}",
            100.0 * (l - gt_len) / gt_len,
            gt_len / t_cm.max(1e-6)
        );
    }
    Ok(())
}

/// What the diagnosis of one run reads once, and the per-vertex quantities
/// it derives on M_outer.
struct Diagnosis {
    outer: Mesh,
    scene: SceneInfo,
    normals: Vec<glam::Vec3>,
    prot: Vec<bool>,
    gt: GtComparison,
    s_cm: f64,
    /// Per vertex: area, closest distance to the GT skin, distance along -n
    /// to the skin (NaN when the ray misses), raw Frosting width.
    areas: Vec<f32>,
    o2s: Vec<f32>,
    ray: Vec<f32>,
    tau: Vec<f32>,
}

impl Diagnosis {
    /// The derived quantities of the loaded run with Frosting's `shell`.
    fn new(run: Loaded, shell: &ShellWidths) -> Result<Self, Box<dyn Error>> {
        let Loaded {
            outer,
            scene,
            normals,
            prot,
            gt,
            ..
        } = run;
        let s_cm = f64::from(scale(&scene));
        let areas = vertex_areas(&outer);
        let o2s = distances_to(&gt.skin, &outer);
        // Distance along -n from the outer vertex to the skin (ray), and the shell width.
        let ray: Vec<f32> = outer
            .positions
            .iter()
            .zip(&normals)
            .map(|(&p, &n)| gt.skin.ray_hit(p, -n, 1.0).unwrap_or(f32::NAN))
            .collect();
        let idx = PointIndex::new(&shell.positions)?;
        let tau = thickness::raw_widths(shell, &idx, &outer.positions);
        Ok(Diagnosis {
            outer,
            scene,
            normals,
            prot,
            gt,
            s_cm,
            areas,
            o2s,
            ray,
            tau,
        })
    }

    /// Prints the skin error of M_outer displaced inward by `d`.
    fn report(&self, label: &str, d: &[f32]) {
        let mut m = self.outer.clone();
        m.positions = postcheck::displace(&self.outer.positions, &self.normals, d);
        let r = self.gt.measure(&m, &self.prot);
        eprintln!(
            "{label:48} mean {:.3} cm ({:.1}%), p95 {:.3} cm",
            r.mean_cm,
            100.0 * r.mean_frac,
            r.p95_cm
        );
    }

    /// `v` with the protected parts' vertices set to zero.
    fn zero(&self, v: &[f32]) -> Vec<f32> {
        v.iter()
            .zip(&self.outer.part)
            .map(|(&x, &p)| if self.prot[p as usize] { 0.0 } else { x })
            .collect()
    }

    /// The GT mean fur thickness of part `name` in cm (0 when unknown).
    fn gt_thickness_cm(&self, name: &str) -> f32 {
        self.scene
            .parts
            .get(name)
            .and_then(|p| p.mean_thickness_cm)
            .unwrap_or(0.0)
    }

    /// The fur (non-protected) vertices.
    fn fur_vertices(&self) -> Vec<usize> {
        (0..self.outer.positions.len())
            .filter(|&i| !self.prot[self.outer.part[i] as usize])
            .collect()
    }

    /// Per part, the area-weighted distances to the skin of M_outer, along
    /// the ray, of tau and of the `root` mesh, and how much of the root is
    /// inside the skin.
    fn print_part_errors(&self, root: &Mesh) {
        let (outer, areas, o2s, ray, tau, s_cm) = (
            &self.outer,
            &self.areas,
            &self.o2s,
            &self.ray,
            &self.tau,
            self.s_cm,
        );
        let r2s = distances_to(&self.gt.skin, root);
        // Signed root error: negative when the root vertex is inside the skin.
        let r_in: Vec<bool> = root
            .positions
            .iter()
            .map(|&p| self.gt.skin.contains(p))
            .collect();
        eprintln!("part            n   gt_th  o2s    ray    tau    r2s   r_inside%");
        for (pi, name) in outer.part_names.iter().enumerate() {
            let (mut w, mut a, mut b, mut c, mut d, mut e, mut wr) =
                (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
            let mut n = 0;
            for i in 0..outer.positions.len() {
                if outer.part[i] as usize != pi {
                    continue;
                }
                n += 1;
                let ar = areas[i] as f64;
                w += ar;
                a += ar * o2s[i] as f64;
                if ray[i].is_finite() {
                    b += ar * ray[i] as f64;
                    wr += ar;
                }
                c += ar * tau[i] as f64;
                d += ar * r2s[i] as f64;
                e += ar * r_in[i] as u8 as f64;
            }
            let th = self.gt_thickness_cm(name);
            eprintln!(
                "{name:12} {n:6} {th:6.2} {:6.2} {:6.2} {:6.2} {:6.2} {:6.1}",
                a / w * s_cm,
                b / wr.max(1e-30) * s_cm,
                c / w * s_cm,
                d / w * s_cm,
                100.0 * e / w
            );
        }
    }

    /// The error of the baseline displacements (none, oracle distances,
    /// tau, constants, GT part thicknesses); returns the GT part thickness
    /// per vertex in scene units.
    fn report_baselines(&self) -> Vec<f32> {
        let (outer, scene, o2s, tau) = (&self.outer, &self.scene, &self.o2s, &self.tau);
        eprintln!("GT thickness {:.3} cm", self.gt.thickness_cm);
        self.report("outer (d = 0)", &vec![0.0; o2s.len()]);
        self.report("d = outer->skin closest distance", &self.zero(o2s));
        let ray_d: Vec<f32> = self
            .ray
            .iter()
            .zip(o2s)
            .map(|(r, o)| if r.is_finite() { *r } else { *o })
            .collect();
        self.report("d = ray distance to skin along -n", &self.zero(&ray_d));
        self.report("d = raw Frosting width tau", &self.zero(tau));
        let med = percentile(tau, 50.0).unwrap_or(0.0);
        self.report("d = global median tau", &self.zero(&vec![med; tau.len()]));
        let gmean = (self.gt.thickness_cm / self.s_cm) as f32;
        self.report(
            "d = GT mean thickness (constant)",
            &self.zero(&vec![gmean; tau.len()]),
        );
        let gpart: Vec<f32> = outer
            .part
            .iter()
            .map(|&p| self.gt_thickness_cm(&outer.part_names[p as usize]) / scale(scene))
            .collect();
        self.report("d = GT part thickness", &self.zero(&gpart));
        let gpart_off: Vec<f32> = gpart.iter().map(|x| x + 0.26 / scale(scene)).collect();
        self.report("d = GT part thickness + 0.26 cm", &self.zero(&gpart_off));
        gpart
    }

    /// Splits the outer-to-skin distance into the visual hull's gap down to
    /// the fur (distance to the nearest GT strand point, strands resampled
    /// every 1 mm) and the fur below it, to see which of the two varies per
    /// vertex.
    fn gap_analysis(&self, gts: &Strands, gpart: &[f32]) -> Res {
        let (outer, areas, o2s, s_cm) = (&self.outer, &self.areas, &self.o2s, self.s_cm);
        let step = 0.1 / scale(&self.scene);
        let mut pts = Vec::new();
        for s in 0..gts.len() {
            for w in gts.strand(s).windows(2) {
                let k = ((w[1] - w[0]).length() / step).ceil().max(1.0) as usize;
                for j in 0..k {
                    pts.push(w[0].lerp(w[1], j as f32 / k as f32));
                }
            }
        }
        let fur_idx = PointIndex::new(&pts)?;
        let gap: Vec<f32> = outer
            .positions
            .iter()
            .map(|&p| fur_idx.nearest(p).1)
            .collect();
        let below: Vec<f32> = o2s.iter().zip(&gap).map(|(a, b)| a - b).collect();
        eprintln!("part          o2s    gap   o2s-gap  gt_th  (cm, area-weighted)");
        for (pi, name) in outer.part_names.iter().enumerate() {
            let (mut w, mut a, mut b) = (0.0f64, 0.0, 0.0);
            for i in 0..outer.positions.len() {
                if outer.part[i] as usize == pi {
                    let ar = areas[i] as f64;
                    w += ar;
                    a += ar * o2s[i] as f64;
                    b += ar * gap[i] as f64;
                }
            }
            let th = self.gt_thickness_cm(name);
            eprintln!(
                "{name:12} {:6.2} {:6.2} {:6.2} {th:6.2}",
                a / w * s_cm,
                b / w * s_cm,
                (a - b) / w * s_cm
            );
        }
        let gap_plus: Vec<f32> = gap.iter().zip(gpart).map(|(a, b)| a + b).collect();
        self.report(
            "d = hull-to-fur gap + GT part thickness",
            &self.zero(&gap_plus),
        );
        self.report("d = hull-to-fur gap only", &self.zero(&gap));
        let below_med = percentile(&below, 50.0).unwrap_or(0.0);
        let gap_plus_c: Vec<f32> = gap.iter().map(|a| a + below_med).collect();
        self.report(
            "d = hull-to-fur gap + median(o2s - gap)",
            &self.zero(&gap_plus_c),
        );
        let fur = self.fur_vertices();
        let var = |v: &[f32]| -> f64 {
            let n = fur.len() as f64;
            let m = fur.iter().map(|&i| v[i] as f64).sum::<f64>() / n;
            fur.iter().map(|&i| (v[i] as f64 - m).powi(2)).sum::<f64>() / n
        };
        eprintln!(
            "variance over fur vertices (cm^2): o2s {:.3}, gap {:.3}, o2s - gap {:.3}",
            var(o2s) * s_cm * s_cm,
            var(&gap) * s_cm * s_cm,
            var(&below) * s_cm * s_cm
        );
        Ok(())
    }

    /// Candidate width readings from Frosting's offsets (crossings and
    /// sigma_n, alone and combined with `gpart`), appended to `cands`.
    fn offset_candidates(off: &Offsets, gpart: &[f32], cands: &mut Vec<(String, Vec<f32>)>) {
        let f = |v: Vec<f32>| -> Vec<f32> { v.into_iter().map(|x| x.max(0.0)).collect() };
        cands.push(("-inner".into(), f(off.inner.iter().map(|x| -x).collect())));
        cands.push(("-outer".into(), f(off.outer.iter().map(|x| -x).collect())));
        cands.push((
            "outer-inner".into(),
            f(off
                .outer
                .iter()
                .zip(&off.inner)
                .map(|(o, i)| o - i)
                .collect()),
        ));
        cands.push((
            "3 sigma_n".into(),
            off.sigma_n.iter().map(|x| 3.0 * x).collect(),
        ));
        let neg_outer: Vec<f32> = off.outer.iter().map(|x| (-x).max(0.0)).collect();
        cands.push((
            "GT part + -outer".into(),
            gpart.iter().zip(&neg_outer).map(|(a, b)| a + b).collect(),
        ));
        cands.push((
            "1.5 sigma_n + -outer".into(),
            off.sigma_n
                .iter()
                .zip(&neg_outer)
                .map(|(a, b)| 1.5 * a + b)
                .collect(),
        ));
    }

    /// Per part, the area-weighted means of the offsets against the oracle.
    fn print_offset_table(&self, off: &Offsets) {
        let (outer, areas, o2s, s_cm) = (&self.outer, &self.areas, &self.o2s, self.s_cm);
        eprintln!("part          o2s    gt     -outer  sigma_n  (cm, area-weighted)");
        for (pi, name) in outer.part_names.iter().enumerate() {
            let (mut w, mut a, mut b, mut c) = (0.0f64, 0.0, 0.0, 0.0);
            for i in 0..outer.positions.len() {
                if outer.part[i] as usize == pi {
                    let ar = areas[i] as f64;
                    w += ar;
                    a += ar * o2s[i] as f64;
                    b += ar * -off.outer[i] as f64;
                    c += ar * off.sigma_n[i] as f64;
                }
            }
            let th = self.gt_thickness_cm(name);
            eprintln!(
                "{name:12} {:6.2} {th:6.2} {:6.2} {:6.2}",
                a / w * s_cm,
                b / w * s_cm,
                c / w * s_cm
            );
        }
    }

    /// Each candidate reading's mean, its Pearson correlation with the
    /// oracle over the fur vertices and the error of displacing by it.
    fn compare_candidates(&self, cands: &[(String, Vec<f32>)]) {
        let fur = self.fur_vertices();
        let corr = |a: &[f32], b: &[f32]| -> f64 {
            let n = fur.len() as f64;
            let ma = fur.iter().map(|&i| a[i] as f64).sum::<f64>() / n;
            let mb = fur.iter().map(|&i| b[i] as f64).sum::<f64>() / n;
            let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
            for &i in &fur {
                let (x, y) = (a[i] as f64 - ma, b[i] as f64 - mb);
                ab += x * y;
                aa += x * x;
                bb += y * y;
            }
            ab / (aa * bb).sqrt().max(1e-30)
        };
        for (label, w) in cands {
            let mean: f64 = fur.iter().map(|&i| w[i] as f64).sum::<f64>() / fur.len() as f64;
            eprintln!(
                "reading {label:20} mean {:.3} cm, pearson vs outer->skin {:.3}",
                mean * self.s_cm,
                corr(w, &self.o2s)
            );
            self.report(&format!("  d = {label}"), &self.zero(w));
        }
    }

    /// Defurs with each candidate as the shell widths, in scene units and in
    /// cm, and reports the solved and post-checked displacements.
    fn solve_candidates(&self, cands: Vec<(String, Vec<f32>)>) -> Res {
        for (label, widths) in cands {
            let sh = ShellWidths {
                positions: self.outer.positions.clone(),
                normals: self.normals.clone(),
                widths,
            };
            for unit in [1.0, self.s_cm] {
                let s = DefurSettings {
                    unit_scale: unit,
                    ..Default::default()
                };
                let res = defur(&self.outer, &sh, &self.prot, &BTreeMap::new(), &s)?;
                self.report(&format!("solve({label}) unit_scale {unit}"), &res.d);
                self.report("  d_solved (no post-check)", &res.d_solved);
            }
        }
        Ok(())
    }
}

/// Where the defurring error of a run comes from, per part and per step (see the file's doc).
fn diagnose(run: Loaded) -> Res {
    let dir = run.dir.clone();
    let shell: ShellWidths = read_json(dir.join("frosting/shell.json"))?;
    let root = read_obj(dir.join("defur/root_mesh.obj"))?;
    let dx = Diagnosis::new(run, &shell)?;
    dx.print_part_errors(&root);
    let gpart = dx.report_baselines();
    if let Ok(gts) = read_hair(dir.join("scene/strands.hair")) {
        dx.gap_analysis(&gts, &gpart)?;
    }
    let mut cands = vec![
        ("oracle o2s".to_string(), dx.o2s.clone()),
        ("frosting tau".to_string(), dx.tau.clone()),
        ("GT part thickness".to_string(), gpart.clone()),
    ];
    if let Ok(off) = read_json::<Offsets>(dir.join("frosting/offsets.json")) {
        if off.inner.len() == dx.outer.positions.len() {
            Diagnosis::offset_candidates(&off, &gpart, &mut cands);
            dx.print_offset_table(&off);
        }
    }
    dx.compare_candidates(&cands);
    dx.solve_candidates(cands)
}
