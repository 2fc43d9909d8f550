//! Stage `blender_scene`: the preset's body with **Blender's own hair**, rendered by Cycles.
//!
//! Why: every other scene of the suite is grown by [`super::fur`] and drawn by [`super::trace`],
//! so a default chosen on them may fit this project's renderer rather than fur. A user's capture
//! comes from other software; this renderer brings one into the same pipelines, with the same
//! outputs and the same ground truth ports, so a benchmark can hold scenes that no code of this
//! project grew or shaded (docs/guide.md, "Scenes rendered by Blender"). It takes
//! `synthetic_scene`'s parameters (a pipeline swaps the kind and keeps them), reads the
//! `blender_*` ones and refuses the ones that only the default renderer reads (noise, camera
//! jitter, mask dilation, segment length); `supersample` is left unused.
//!
//! What runs: the stage builds the preset's body and skin exactly as the default renderer does
//! ([`super::generate`]), writes `skin.obj` / `labels.obj`, then runs Blender
//! (`blender -b --factory-startup --python-exit-code 1 -P fur_capture.py -- ...`, the script
//! next to this module, embedded in the binary and written to a scratch folder under the `views`
//! output) twice: once to grow the hair and render the views, once with the regrow seed and
//! `--hair-only` for the ceiling's `regrown.hair`. The executable is `$FURE_BLENDER`, else
//! `blender` on the `PATH`; without it the stage fails saying so.
//!
//! The hair (Blender's particle hair, one system over every fur part; the script's doc): its
//! choices follow the default renderer's rules so the two stay comparable. Strand count
//! `strands_per_px2` per pixel footprint of fur skin; root radius half of `width_px` pixel
//! footprints; length `blender_length_cm` (unset: the mean length of the preset's own GT fur,
//! so a Blender fox is about as long-haired as ours), every strand about the same length;
//! combed toward the tail and the ground and rising `blender_rise` along the normal (0.15 lies
//! flat at about 11 degrees, 0.6 rises about 40). Parts the preset grows no fur on (eyes,
//! nose, pads, horns, hooves) stay bare. Views: `views` training and `test_views` held-out
//! RGBA PNGs at `resolution`, Cycles with `blender_samples` samples, Filmic, Blender's camera
//! convention (a NeRF `transforms.json`); no masks, fur masks or depth maps, which a capture
//! does not have either.
//!
//! Ground truth (`strands.hair`, `regrown.hair`, `strands_ply.ply`, `scene.json`'s per-part
//! statistics): the hair Blender rendered, in scene units. Each strand's part is the label of
//! the skin vertex nearest its root; `mean_length_cm`, `density_per_cm2` and
//! `mean_thickness_cm` are computed as the default renderer's are (the strand's highest point
//! above its root's tangent plane, the part's skin area).
//!
//! Determinism: the hair and the Cycles noise are seeded (`seed`; the regrown hair
//! [`blender_regrow_seed`]); the bytes are Blender's, so another Blender version may differ
//! (`report.json` names the version that ran).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use serde_json::json;

use super::fur::PartStats;
use super::{
    generate, scene_info_of, Generated, Settings, SyntheticSceneParams, SyntheticSceneStage,
};
use crate::data::strands::Strands;
use crate::formats;
use crate::maths::geom::PointIndex;

/// The Blender script (grows, renders and exports the hair).
pub const SCRIPT: &str = include_str!("fur_capture.py");

/// Environment variable naming the Blender executable (else `blender` on the `PATH`).
pub const BLENDER_ENV: &str = "FURE_BLENDER";

/// Default `blender_rise`: hair rising about 22 degrees over the skin, between the flat and the
/// upright captures of docs/history.md.
pub const DEFAULT_RISE: f32 = 0.3;

/// Default Cycles samples per pixel.
pub const DEFAULT_SAMPLES: usize = 16;

/// Blender's particle seed is a 32-bit int: seeds above this are refused in `validate`.
pub const MAX_SEED: u64 = 1 << 30;

/// The Blender hair of the ceiling's regrown animal: another particle seed.
pub fn blender_regrow_seed(seed: u64) -> u64 {
    seed + MAX_SEED
}

/// The `blender_scene` stage.
pub struct BlenderSceneStage;

impl Stage for BlenderSceneStage {
    fn kind(&self) -> &'static str {
        "blender_scene"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "A synthetic animal's body (the synthetic_scene presets) with Blender's own particle hair, \
         rendered by Cycles (needs Blender: $FURE_BLENDER or `blender` on the PATH); the same \
         outputs and ground truth as synthetic_scene, views without masks or depth."
    }
    fn params(&self) -> Vec<ParamSpec> {
        SyntheticSceneParams::specs()
    }
    fn inputs(&self, _params: &Params) -> Vec<PortSpec> {
        Vec::new()
    }
    fn outputs(&self, params: &Params) -> Vec<PortSpec> {
        SyntheticSceneStage.outputs(params)
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        let st = Settings::from_params_of(params, true)?;
        let p = super::presets::preset(&st.preset)?;
        super::presets::validate_overrides(&p, &st.parts)
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let st = Settings::from_params_of(ctx.params, true)?;
        let bl = st
            .blender
            .clone()
            .expect("blender settings for kind blender_scene");
        run(&st, &bl, ctx)
    }
}

/// The Blender renderer's own settings.
#[derive(Debug, Clone, PartialEq)]
pub struct BlenderSettings {
    pub rise: f32,
    pub length_cm: Option<f32>,
    pub samples: usize,
}

/// Builds the body, runs Blender and writes every output of `synthetic_scene`.
pub fn run(st: &Settings, bl: &BlenderSettings, ctx: &StageContext<'_>) -> Result<(), StageError> {
    let t0 = Instant::now();
    ctx.progress.message("building the body");
    let g = generate(st)?;
    let views_dir = ctx.output("views")?.to_path_buf();
    let skin_path = ctx.output("skin")?;
    formats::obj::write_obj(skin_path, &g.mesh)?;
    formats::obj::write_obj(ctx.output("labels")?, &g.mesh)?;

    let hair = HairChoice::new(&g, st, bl);
    let scratch = views_dir.join(".blender");
    std::fs::create_dir_all(&scratch).map_err(|e| StageError::io(&scratch, e))?;
    let script = scratch.join("fur_capture.py");
    std::fs::write(&script, SCRIPT).map_err(|e| StageError::io(&script, e))?;

    ctx.progress
        .message("Blender: growing and rendering the hair");
    let capture = scratch.join("capture");
    let mut args = hair.args(st.seed, bl);
    args.extend(flags(&[
        ("--views", st.views.to_string()),
        ("--test-views", st.test_views.to_string()),
        ("--resolution", st.resolution.to_string()),
    ]));
    let version = run_blender(&script, skin_path, &capture, &args, ctx)?;
    ctx.progress.message("Blender: the regrown hair");
    let regrown_dir = scratch.join("regrown");
    let mut args = hair.args(blender_regrow_seed(st.seed), bl);
    args.push("--hair-only".into());
    run_blender(&script, skin_path, &regrown_dir, &args, ctx)?;

    for entry in ["train", "test", "transforms.json", "transforms_test.json"] {
        let from = capture.join("views").join(entry);
        let to = views_dir.join(entry);
        std::fs::rename(&from, &to).map_err(|e| StageError::io(&from, e))?;
    }
    let labelled = Labelled::new(&g)?;
    let gt = labelled.read(&capture.join("gt/strands.hair"), hair.radius)?;
    let regrown = labelled
        .read(&regrown_dir.join("gt/strands.hair"), hair.radius)?
        .strands;
    std::fs::remove_dir_all(&scratch).map_err(|e| StageError::io(&scratch, e))?;

    formats::hair::write_hair(ctx.output("strands")?, &gt.strands)?;
    formats::hair::write_hair(ctx.output("regrown")?, &regrown)?;
    formats::ply::write_ply_strands(ctx.output("strands_ply")?, &gt.strands)?;
    formats::json::write_json(ctx.output("scene")?, &scene_info_of(&g, &gt.stats))?;

    let pixel_cm = g.pixel_units * g.s_cm;
    let note = format!(
        "Blender {version}: {} strands, mean length {:.2} cm (asked {:.2}), rising {:.2}, {} + {} \
         views at {} px (pixel {pixel_cm:.3} cm), {} samples",
        gt.strands.len(),
        gt.mean_length_cm(),
        hair.length * g.s_cm,
        bl.rise,
        st.views,
        st.test_views,
        st.resolution,
        bl.samples
    );
    ctx.progress.note(&note);
    let report = json!({
        "preset": st.preset,
        "renderer": "blender",
        "blender_version": version,
        "seed": st.seed,
        "s_cm": g.s_cm,
        "resolution": st.resolution,
        "views": st.views,
        "test_views": st.test_views,
        "pixel_cm": pixel_cm,
        "strands": gt.strands.len(),
        "hair": {
            "count": hair.count,
            "length_cm": hair.length * g.s_cm,
            "radius_cm": hair.radius * g.s_cm,
            "rise": bl.rise,
            "samples": bl.samples,
            "bare_parts": hair.bare,
        },
        "notes": [note],
        "seconds": { "total": t0.elapsed().as_secs_f64() },
    });
    formats::json::write_json(ctx.output("report")?, &report)?;
    Ok(())
}

/// What Blender is asked to grow, from the default renderer's rules (module doc).
struct HairChoice {
    count: usize,
    /// Scene units.
    length: f32,
    /// Root radius, scene units.
    radius: f32,
    bare: Vec<String>,
}

impl HairChoice {
    fn new(g: &Generated, st: &Settings, bl: &BlenderSettings) -> HairChoice {
        let fur_parts: Vec<&str> = g
            .preset
            .parts
            .iter()
            .filter(|(_, f)| f.fur)
            .map(|(n, _)| *n)
            .collect();
        let stats = |n: &str| g.fur.stats.get(n);
        let area_cm2: f64 = fur_parts
            .iter()
            .filter_map(|n| stats(n))
            .map(|s| s.area_cm2)
            .sum();
        let pixel_cm = (g.pixel_units * g.s_cm) as f64;
        let count = (st.strands_per_px2 as f64 * area_cm2 / (pixel_cm * pixel_cm)).round() as usize;
        let (sum, n) = fur_parts
            .iter()
            .filter_map(|n| stats(n))
            .fold((0.0, 0usize), |(s, c), p| {
                (s + p.sum_length_cm, c + p.strands)
            });
        let mean_cm = bl
            .length_cm
            .unwrap_or(if n > 0 { (sum / n as f64) as f32 } else { 1.0 });
        HairChoice {
            count: count.max(1),
            length: mean_cm / g.s_cm,
            radius: 0.5 * st.width_px * g.pixel_units,
            bare: g
                .preset
                .parts
                .iter()
                .filter(|(_, f)| !f.fur)
                .map(|(n, _)| n.to_string())
                .collect(),
        }
    }

    fn args(&self, seed: u64, bl: &BlenderSettings) -> Vec<String> {
        // An empty `--bare` would mean the script's own default; a name no mesh has means none.
        let bare = if self.bare.is_empty() {
            "-".to_string()
        } else {
            self.bare.join(",")
        };
        flags(&[
            ("--hairs", self.count.to_string()),
            ("--length", self.length.to_string()),
            ("--radius", self.radius.to_string()),
            ("--rise", bl.rise.to_string()),
            ("--samples", bl.samples.to_string()),
            ("--seed", seed.to_string()),
            ("--bare", bare),
        ])
    }
}

/// Command-line flags with their values, in order.
fn flags(pairs: &[(&str, String)]) -> Vec<String> {
    pairs
        .iter()
        .flat_map(|(flag, value)| [flag.to_string(), value.clone()])
        .collect()
}

/// The Blender executable: `$FURE_BLENDER`, else `blender`.
pub fn blender_executable() -> PathBuf {
    std::env::var_os(BLENDER_ENV)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("blender"))
}

/// Runs the script into `out`; returns the Blender version it printed. Polls so that an
/// interrupted run stops Blender too.
fn run_blender(
    script: &Path,
    skin: &Path,
    out: &Path,
    args: &[String],
    ctx: &StageContext<'_>,
) -> Result<String, StageError> {
    let exe = blender_executable();
    std::fs::create_dir_all(out).map_err(|e| StageError::io(out, e))?;
    let log_path = out.join("blender.log");
    let log = std::fs::File::create(&log_path).map_err(|e| StageError::io(&log_path, e))?;
    let log_err = log.try_clone().map_err(|e| StageError::io(&log_path, e))?;
    let mut child = Command::new(&exe)
        .args(["-b", "--factory-startup", "--python-exit-code", "1", "-P"])
        .arg(script)
        .arg("--")
        .arg(skin)
        .arg(out)
        .args(args)
        .stdin(Stdio::null())
        .stdout(log)
        .stderr(log_err)
        .spawn()
        .map_err(|e| {
            StageError::failed(format!(
                "renderer = \"blender\" needs Blender: cannot run `{}` ({e}); install it \
                 (Debian: apt-get install blender) or set {BLENDER_ENV} to its path",
                exe.display()
            ))
        })?;
    let status = loop {
        if let Some(s) = child.try_wait().map_err(|e| StageError::io(&log_path, e))? {
            break s;
        }
        if ctx.progress.interrupted() {
            let _ = child.kill();
            let _ = child.wait();
            return Err(StageError::Interrupted);
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let text = std::fs::read_to_string(&log_path).unwrap_or_default();
    if !status.success() {
        let tail: Vec<&str> = text.lines().rev().take(12).collect();
        let tail: Vec<&str> = tail.into_iter().rev().collect();
        return Err(StageError::failed(format!(
            "Blender (`{}`) failed ({status}); its output ends:\n{}",
            exe.display(),
            tail.join("\n")
        )));
    }
    Ok(text
        .lines()
        .find_map(|l| l.strip_prefix("fur_capture: Blender "))
        .and_then(|l| l.split(',').next())
        .unwrap_or("(unknown version)")
        .to_string())
}

/// The skin's labels and normals, to label Blender's strands and measure them.
struct Labelled<'a> {
    g: &'a Generated,
    index: PointIndex,
}

/// Blender's hair, labelled, with its per-part statistics.
struct BlenderHair {
    strands: Strands,
    stats: BTreeMap<String, PartStats>,
}

impl BlenderHair {
    /// Mean arc length over every strand, cm.
    fn mean_length_cm(&self) -> f32 {
        let (sum, n) = self
            .stats
            .values()
            .fold((0.0, 0), |(s, n), p| (s + p.sum_length_cm, n + p.strands));
        (sum / n.max(1) as f64) as f32
    }
}

impl<'a> Labelled<'a> {
    fn new(g: &'a Generated) -> Result<Self, StageError> {
        let index = PointIndex::new(&g.mesh.positions)
            .map_err(|e| StageError::failed(format!("skin mesh: {e}")))?;
        Ok(Labelled { g, index })
    }

    /// Reads Blender's `.hair`: each strand gets the part of the skin vertex nearest its root,
    /// a width and a colour, and enters that part's statistics as the default renderer's
    /// strands do (arc length; highest point above the root's tangent plane, the vertex normal).
    fn read(&self, path: &Path, radius: f32) -> Result<BlenderHair, StageError> {
        let g = self.g;
        let raw = formats::hair::read_hair(path)?;
        let mut strands = Strands::new();
        strands.part_names = g.mesh.part_names.clone();
        let mut stats: BTreeMap<String, PartStats> = g
            .fur
            .stats
            .iter()
            .map(|(name, st)| {
                let area = PartStats {
                    area_cm2: st.area_cm2,
                    ..Default::default()
                };
                (name.clone(), area)
            })
            .collect();
        for i in 0..raw.len() {
            let pts = raw.strand(i);
            let Some(&root) = pts.first() else { continue };
            if !pts.iter().all(|p| p.is_finite()) {
                return Err(StageError::failed(format!(
                    "Blender's hair ({}): strand {i} has a non-finite point",
                    path.display()
                )));
            }
            let (v, _) = self.index.nearest(root);
            let part = g.mesh.part[v];
            let height = pts
                .iter()
                .map(|p| (*p - root).dot(g.mesh.normals[v]))
                .fold(0.0f32, f32::max);
            if let Some(st) = stats.get_mut(g.mesh.part_name(v)) {
                st.add_strand((raw.length(i) * g.s_cm) as f64, (height * g.s_cm) as f64);
            }
            // Blender's Principled Hair at melanin 0.55, redness 0.8: a mid brown.
            strands.push(pts, part, 2.0 * radius, [0.30, 0.16, 0.08]);
        }
        stats.values_mut().for_each(PartStats::finish);
        Ok(BlenderHair { strands, stats })
    }
}
