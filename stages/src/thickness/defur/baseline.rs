//! `defur_baseline`: NeuralFur's defurring, for comparison (prior-art.md).
//!
//! NeuralFur asks a chat model for a per-part "effective fur thickness" in
//! cm, multiplies it by the metric scale (here: divides by `s_cm`, cm per
//! scene unit), smooths that per-vertex scalar with 100 iterations of
//! uniform Laplacian smoothing and shrinks the outer mesh along its normals.
//!
//! Choices:
//! - Thicknesses come from a per-species table ([`species_thickness_cm`],
//!   parameter `species`), the stand-in for NeuralFur's chat-model answer.
//!   `panda` (the default) is NeuralFur's own reference list mapped onto our
//!   part names: torso 3.5 (body), belly 4, neck 4.5, tail 3.5, head, muzzle
//!   and ears 1.5 (face), legs 3.5 (body), paws 1.5. The other species are
//!   what a person writes down for "how deep is this animal's coat, per body
//!   region" from general knowledge of the animal (encyclopedia descriptions
//!   of coat length: a tiger's short sleek coat, a fox's and a wolf's long
//!   winter coat with a thick neck ruff and brush, a bison's shaggy mane over
//!   short-haired hindquarters, a short-haired house cat, a lynx's dense
//!   winter coat, an Old English sheepdog's long shaggy coat over the whole
//!   body, face and legs included, a poodle's dense curly coat left long over
//!   body, head, ears and legs with a shaved muzzle), taken as about half
//!   the hair length since fur lies at a shallow angle, rounded to 0.5 cm
//!   (0.3 for the cat's face). They are coarse on purpose, never read from a
//!   scene, and written without looking at `scene.json`; but they were written
//!   by the team that built the synthetic presets, so they are not independent
//!   of the presets' authorship, only of their data. `thickness_cm` overrides
//!   single parts; other fur parts use `default_thickness_cm`; protected
//!   (bald) parts 0.
//! - One smoothing iteration is `s_i <- s_i + step (mean_{j ~ i} s_j - s_i)`
//!   with `step = 0.5` over all vertices (bald ones included, as their 0
//!   enters the scalar field): a plain `step = 1` Jacobi average oscillates
//!   on near-bipartite meshes.
//! - NeuralFur then rebuilds the surface from an SDF (256^3) by marching
//!   cubes; we keep the outer mesh's topology instead (same surface up to
//!   re-meshing), so the result is comparable vertex for vertex.

use std::collections::BTreeMap;
use std::time::Instant;

use fure_stage_api::{
    ensure_finite, ParamSpec, ParamType, Params, PortSpec, Stage, StageContext, StageError,
};
use glam::Vec3;

use super::{scale_from, vertex_normals, GtComparison, DEFAULT_PROTECTED};
use crate::data::mesh::Mesh;
use crate::formats::json::write_json;
use crate::formats::obj::{read_mesh, write_obj};
use crate::maths::geom::vertex_neighbours;
use crate::surface::parts::{protected_names, protected_parts};

/// NeuralFur's reference thicknesses (cm) on our part names.
pub const DEFAULT_THICKNESS_CM: &[(&str, f32)] = &[
    ("torso", 3.5),
    ("belly", 4.0),
    ("neck", 4.5),
    ("tail", 3.5),
    ("head", 1.5),
    ("muzzle", 1.5),
    ("ears", 1.5),
    ("front_legs", 3.5),
    ("hind_legs", 3.5),
    ("legs", 3.5),
    ("paws", 1.5),
];

/// The species `defur_baseline.species` accepts.
pub const SPECIES: &[&str] = &[
    "panda", "tiger", "fox", "cat", "bison", "wolf", "lynx", "sheepdog", "poodle",
];

/// Coarse per-part effective fur thickness (cm) of a species (module doc); `None` for an
/// unknown species.
pub fn species_thickness_cm(species: &str) -> Option<&'static [(&'static str, f32)]> {
    Some(match species {
        "panda" => DEFAULT_THICKNESS_CM,
        "tiger" => &[
            ("torso", 1.0),
            ("belly", 1.5),
            ("neck", 1.5),
            ("tail", 1.0),
            ("head", 0.5),
            ("muzzle", 0.5),
            ("ears", 0.5),
            ("front_legs", 1.0),
            ("hind_legs", 1.0),
            ("legs", 1.0),
            ("paws", 0.5),
        ],
        "fox" => &[
            ("torso", 2.0),
            ("belly", 2.0),
            ("neck", 2.5),
            ("tail", 3.5),
            ("head", 1.0),
            ("muzzle", 0.5),
            ("ears", 0.5),
            ("front_legs", 1.0),
            ("hind_legs", 1.0),
            ("legs", 1.0),
            ("paws", 0.5),
        ],
        "cat" => &[
            ("torso", 1.0),
            ("belly", 1.0),
            ("neck", 1.0),
            ("tail", 1.0),
            ("head", 0.5),
            ("muzzle", 0.3),
            ("ears", 0.3),
            ("front_legs", 0.5),
            ("hind_legs", 0.5),
            ("legs", 0.5),
            ("paws", 0.3),
        ],
        "bison" => &[
            ("torso", 2.5),
            ("shoulders", 8.0),
            ("belly", 3.0),
            ("neck", 8.0),
            ("tail", 3.0),
            ("head", 6.0),
            ("muzzle", 1.5),
            ("ears", 1.5),
            ("front_legs", 2.0),
            ("hind_legs", 1.0),
            ("legs", 1.5),
            ("paws", 1.0),
        ],
        "wolf" => &[
            ("torso", 3.5),
            ("belly", 2.5),
            ("neck", 5.0),
            ("tail", 4.0),
            ("head", 1.0),
            ("muzzle", 0.5),
            ("ears", 1.0),
            ("front_legs", 1.0),
            ("hind_legs", 1.5),
            ("legs", 1.0),
            ("paws", 0.5),
        ],
        "lynx" => &[
            ("torso", 2.0),
            ("belly", 2.0),
            ("neck", 2.5),
            ("tail", 2.0),
            ("head", 1.0),
            ("muzzle", 0.5),
            ("ears", 0.5),
            ("front_legs", 1.5),
            ("hind_legs", 1.5),
            ("legs", 1.5),
            ("paws", 1.0),
        ],
        "sheepdog" => &[
            ("torso", 5.0),
            ("belly", 4.5),
            ("neck", 5.5),
            ("tail", 3.0),
            ("head", 3.5),
            ("muzzle", 2.0),
            ("ears", 3.5),
            ("front_legs", 3.0),
            ("hind_legs", 3.5),
            ("legs", 3.0),
            ("paws", 2.0),
        ],
        "poodle" => &[
            ("torso", 2.5),
            ("belly", 2.5),
            ("neck", 2.5),
            ("tail", 2.5),
            ("head", 3.0),
            ("muzzle", 0.5),
            ("ears", 3.0),
            ("front_legs", 2.0),
            ("hind_legs", 2.0),
            ("legs", 2.0),
            ("paws", 1.0),
        ],
        _ => return None,
    })
}

/// The baseline shrink of every vertex (scene units) after smoothing.
pub fn baseline_shrink(
    mesh: &Mesh,
    part_thickness: &[f32],
    iterations: usize,
    step: f32,
) -> Vec<f32> {
    let mut s: Vec<f32> = mesh
        .part
        .iter()
        .map(|&p| part_thickness.get(p as usize).copied().unwrap_or(0.0))
        .collect();
    let nb = vertex_neighbours(mesh);
    let mut next = s.clone();
    for _ in 0..iterations {
        for i in 0..s.len() {
            if nb[i].is_empty() {
                next[i] = s[i];
                continue;
            }
            let mean = nb[i].iter().map(|&j| s[j as usize]).sum::<f32>() / nb[i].len() as f32;
            next[i] = s[i] + step * (mean - s[i]);
        }
        std::mem::swap(&mut s, &mut next);
    }
    s
}

fure_stage_api::stage_params! {
    /// The `defur_baseline` stage's parameters.
    pub struct DefurBaselineParams {
        /// per-species thickness table (panda: NeuralFur's reference list; module doc)
        species: String = string("panda").choices(SPECIES),
        /// per-part fur thickness in cm (overrides the species table)
        thickness_cm: BTreeMap<String, f32> = table(),
        /// thickness of fur parts with no entry
        default_thickness_cm: f32 = float(3.5).min(0.0),
        /// Laplacian smoothing iterations
        iterations: usize = int(100).range(0.0, 100000.0),
        /// fraction of the way to the neighbour mean per iteration
        smoothing_step: f32 = float(0.5).range(0.0, 1.0),
        /// centimetres per scene unit, when no `scale` input is connected
        s_cm: Option<f64> = optional(ParamType::Float).positive(),
        /// bald part names (thickness 0), case-insensitive
        protected_parts: Vec<String> = str_list(DEFAULT_PROTECTED),
    }
}

/// The `defur_baseline` stage.
pub struct DefurBaselineStage;

impl Stage for DefurBaselineStage {
    fn kind(&self) -> &'static str {
        "defur_baseline"
    }
    fn version(&self) -> u32 {
        2
    }
    fn doc(&self) -> &'static str {
        "NeuralFur's defurring for comparison: per-part thickness (cm, as a chat model would give it) \
         converted with the metric scale, uniform Laplacian smoothing, shrink along the normals."
    }
    fn params(&self) -> Vec<ParamSpec> {
        DefurBaselineParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file("outer", "obj", "M_outer with part groups"),
            PortSpec::file(
                "scale",
                "json",
                "metric scale: the `lengths` output (field s_cm)",
            )
            .optional(),
            PortSpec::file("protected", "json", "extra bald part names (JSON list)").optional(),
            PortSpec::file("gt_skin", "obj", "GT skin, for metrics only").optional(),
            PortSpec::file("gt_scene", "json", "GT scene.json, for metrics only").optional(),
        ]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file(
                "root_mesh",
                "obj",
                "the baseline's defurred mesh (outer topology and parts)",
            ),
            PortSpec::file(
                "metrics",
                "json",
                "per-part thickness used, mean shrink, and (with GT) distances to the skin",
            ),
        ]
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        DefurBaselineParams::from_params(params).map(|_| ())
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let p = DefurBaselineParams::from_params(ctx.params)?;
        let outer = read_mesh(ctx, "outer")?;
        let s_cm = scale_from(ctx, p.s_cm)?.ok_or_else(|| {
            StageError::param(
                "s_cm",
                "the baseline's thicknesses are in cm and need the metric scale: connect the `scale` input (the lengths stage) or set `s_cm`",
            )
        })?;
        let species = p.species.as_str();
        let mut table: BTreeMap<String, f32> = species_thickness_cm(species)
            .ok_or_else(|| {
                StageError::param(
                    "species",
                    format!(
                        "unknown species `{species}`; expected one of {}",
                        SPECIES.join(", ")
                    ),
                )
            })?
            .iter()
            .map(|(k, v)| (k.to_string(), *v))
            .collect();
        table.extend(p.thickness_cm.clone());
        let default_cm = p.default_thickness_cm;
        let names = protected_names(ctx, &p.protected_parts)?;
        let prot = protected_parts(&outer.part_names, &names);
        let part_cm: Vec<f32> = outer
            .part_names
            .iter()
            .zip(&prot)
            .map(|(n, &pr)| {
                if pr {
                    0.0
                } else {
                    table.get(n).copied().unwrap_or(default_cm)
                }
            })
            .collect();
        let part_scene: Vec<f32> = part_cm.iter().map(|c| c / s_cm).collect();
        let t0 = Instant::now();
        let shrink = baseline_shrink(&outer, &part_scene, p.iterations, p.smoothing_step);
        let normals = vertex_normals(&outer);
        let mut root = outer.clone();
        root.positions = outer
            .positions
            .iter()
            .zip(&normals)
            .zip(&shrink)
            .map(|((&x, &n), &s)| x - s * n)
            .collect::<Vec<Vec3>>();
        root.recompute_normals();
        ensure_finite(
            "baseline root mesh",
            root.positions.iter().flat_map(|v| v.to_array()),
        )?;
        let seconds = t0.elapsed().as_secs_f64();
        write_obj(ctx.output("root_mesh")?, &root)?;

        let mut m = serde_json::Map::new();
        let thick: serde_json::Map<String, serde_json::Value> = outer
            .part_names
            .iter()
            .zip(&part_cm)
            .map(|(n, &c)| (n.clone(), c.into()))
            .collect();
        m.insert("thickness_cm".into(), thick.into());
        m.insert("s_cm".into(), s_cm.into());
        let mean_shrink =
            shrink.iter().map(|&x| x as f64).sum::<f64>() / shrink.len().max(1) as f64;
        m.insert("mean_shrink_cm".into(), (mean_shrink * s_cm as f64).into());
        m.insert("seconds".into(), seconds.into());
        if let Some(gt) = GtComparison::load(ctx, &outer, &prot)? {
            let b = gt.measure(&root, &prot);
            m.insert("gt_fur_thickness_cm".into(), gt.thickness_cm.into());
            m.insert("baseline_to_skin_mean_cm".into(), b.mean_cm.into());
            m.insert("baseline_to_skin_p95_cm".into(), b.p95_cm.into());
            m.insert("baseline_to_skin_mean_frac".into(), b.mean_frac.into());
            m.insert("baseline_to_skin_p95_frac".into(), b.p95_frac.into());
        }
        write_json(ctx.output("metrics")?, &serde_json::Value::Object(m))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smoothing_blends_part_thickness_and_keeps_constants() {
        let mesh = super::super::tests::icosphere(1.0, 2, 0.5);
        // Constant field stays constant.
        let s = baseline_shrink(&mesh, &[0.2, 0.2], 100, 0.5);
        assert!(s.iter().all(|&x| (x - 0.2).abs() < 1e-5));
        // Two parts: values end strictly between and the part means order is kept.
        let s = baseline_shrink(&mesh, &[0.2, 0.0], 100, 0.5);
        let (mut a, mut na, mut b, mut nb) = (0.0, 0, 0.0, 0);
        for (i, &x) in s.iter().enumerate() {
            assert!((0.0..=0.2).contains(&x));
            if mesh.part[i] == 0 {
                a += x;
                na += 1;
            } else {
                b += x;
                nb += 1;
            }
        }
        assert!(a / na as f32 > b / nb as f32);
        assert!(
            b / (nb as f32) > 0.0,
            "smoothing spreads thickness into the cap"
        );
    }
}
