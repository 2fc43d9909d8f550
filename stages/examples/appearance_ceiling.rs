//! The held-out PSNR the strand learners' image formation reaches when the geometry is right: the
//! ground-truth strands, resampled to the learners' points per strand and given the learner's
//! strand width (the median of `codec/strands.hair`; the GT files' width is its own renderer's
//! and several times larger), over the GT skin, coloured
//! by the codec's own colour fit (the start fit under the training opacity, then the refit under
//! the held-out renders' width coverage with its refinements, as `codec_strands` does; the codec's
//! `metrics.json` says which) and rendered into
//! the held-out views. What the learners' held-out PSNR can reach with per-strand colours; the
//! gap to it is geometry, the gap above it is the appearance model. Needs a synthetic scene.
//!
//! ```sh
//! fure run pipelines/tiger.toml --until evaluate
//! cargo run -p fure-stages --release --example appearance_ceiling -- out/tiger [points_per_strand ...]
//! ```
//!
//! Prints, per points-per-strand count (default 8, the learners'), the mean PSNR and SSIM over the
//! held-out views with one colour per strand and with a colour ramp from root to tip
//! (`color_ramp`), beside the learner's own from `evaluate/metrics.json`, and how much of the
//! error lies just outside the photos' outline (`common::OutlineError`).

mod common;

use fure_stages::data::strands::Strands;
use fure_stages::evaluation::evaluate::image_metrics;
use fure_stages::formats::hair::read_hair;
use fure_stages::formats::json::read_json;
use fure_stages::formats::obj::read_obj;
use fure_stages::growth::learn::image::{ColorFitPass, Formation, ImageConfig, ImageLosses};
use fure_stages::growth::learn::stage::{LearnMetrics, LearnParams};
use fure_stages::growth::strand_basis::resample_count;
use fure_stages::render::device::Renderer;

use common::Res;

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

fn run() -> Res<()> {
    let (dir, args) =
        common::out_dir_and_args("appearance_ceiling <out/pipeline> [points_per_strand ...]")?;
    let dir = dir.as_path();
    let counts: Vec<usize> = if !args.is_empty() {
        args.iter()
            .map(|a| {
                a.parse()
                    .map_err(|_| format!("points per strand: {a:?} is not a count"))
            })
            .collect::<Result<_, _>>()?
    } else {
        vec![8]
    };
    let views = dir.join("scene/views");
    let gt = read_hair(dir.join("scene/strands.hair"))?;
    let skin = read_obj(dir.join("scene/skin.obj"))?;
    let learned = read_hair(dir.join("codec/strands.hair"))?;
    let mut w = learned.width.clone();
    w.sort_by(f32::total_cmp);
    let width = *w
        .get(w.len() / 2)
        .ok_or("codec/strands.hair has no strands")?;
    println!(
        "strand width: learner's median {width:.3e}, GT file's median {:.3e} (scene units)",
        {
            let mut g = gt.width.clone();
            g.sort_by(f32::total_cmp);
            g.get(g.len() / 2).copied().unwrap_or(f32::NAN)
        }
    );
    if let Ok(m) = read_json::<serde_json::Value>(dir.join("evaluate/metrics.json")) {
        println!(
            "learner (evaluate/metrics.json): PSNR {:.2} dB, SSIM {:.3}",
            m["psnr"].as_f64().unwrap_or(f64::NAN),
            m["ssim"].as_f64().unwrap_or(f64::NAN)
        );
    }
    // The learners' shared defaults and the codec's own colour fit, rendering on the CPU.
    let own = read_json::<LearnMetrics>(dir.join("codec/metrics.json"))?.colors;
    let base = LearnParams::defaults()?.image_config(Renderer::Cpu, own);
    for (l, color_ramp) in counts.into_iter().flat_map(|l| [(l, false), (l, true)]) {
        let cfg = ImageConfig {
            color_ramp,
            ..base.clone()
        };
        let mut points = Vec::with_capacity(gt.len() * l);
        for s in 0..gt.len() {
            points.extend(resample_count(gt.strand(s), l));
        }
        let mut img = ImageLosses::new(&views, None, &skin, vec![width; gt.len()], &cfg)?;
        img.fit_colors(&points, l, Formation::Training, ColorFitPass::Start)?;
        let coloured = img.fit_colors(&points, l, Formation::HeldOut, ColorFitPass::Final)?;
        let mut strands = Strands::new();
        for (s, c) in img.colors().iter().enumerate() {
            strands.push(&points[s * l..(s + 1) * l], gt.part[s], width, *c);
        }
        let tmp = tempfile::tempdir()?;
        img.render_test_views(&strands, tmp.path())?;
        let (psnr, ssim, n) = image_metrics(tmp.path(), &views, [0.0; 3])?;
        println!(
            "GT strands, {l} points each ({} strands, {:.1} % coloured), {}: PSNR {psnr:.2} dB, SSIM {ssim:.3} over {n} held-out views",
            gt.len(),
            100.0 * coloured,
            if color_ramp { "colour ramps" } else { "one colour each" },
        );
        println!(
            "  {}",
            common::OutlineError::measure(tmp.path(), &views)?.describe()
        );
    }
    Ok(())
}
