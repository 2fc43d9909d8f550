//! How much the strands' coverage helps the held-out renders: a learner's own final strands
//! (`codec/strands.hair`, or another learner's), their widths scaled by `k`, rendered as the
//! learners render their held-out views (over the defurred body's occluders, colours from the
//! closed-form colour fit: the start fit under the training opacity, the final one under the
//! width coverage, with the learner's own colour ramps and refinements, as `codec_strands` does).
//! `k = 1` reproduces the learner's held-out PSNR; `k` near 0 leaves the body's occluders
//! alone, coloured from the same views.
//!
//! ```sh
//! fure run pipelines/tiger.toml --until evaluate
//! cargo run -p fure-stages --release --example strand_coverage -- out/tiger [codec] [k ...]
//! ```
//!
//! Prints the mean PSNR and SSIM over the held-out views for each `k` (default 1, 0.5, 0.001),
//! and how much of the error lies just outside the photos' outline (`common::OutlineError`).

mod common;

use fure_stages::data::strands::Strands;
use fure_stages::evaluation::evaluate::image_metrics;
use fure_stages::formats::hair::read_hair;
use fure_stages::formats::json::read_json;
use fure_stages::formats::obj::read_obj;
use fure_stages::growth::learn::image::{ColorFitPass, Formation, ImageLosses};
use fure_stages::growth::learn::stage::{LearnMetrics, LearnParams};
use fure_stages::render::device::Renderer;

use common::Res;

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

fn run() -> Res<()> {
    let (dir, args) =
        common::out_dir_and_args("strand_coverage <out/pipeline> [learner stage] [k ...]")?;
    let dir = dir.as_path();
    let learner = args.first().map_or("codec", String::as_str);
    let ks: Vec<f32> = match args.get(1..) {
        Some(rest) if !rest.is_empty() => rest
            .iter()
            .map(|a| match a.parse::<f32>() {
                Ok(k) if k.is_finite() && k > 0.0 => Ok(k),
                _ => Err(format!("width scale {a:?}: expected a positive number")),
            })
            .collect::<Result<_, _>>()?,
        _ => vec![1.0, 0.5, 0.001],
    };
    let views = dir.join("scene/views");
    let learned = read_hair(dir.join(format!("{learner}/strands.hair")))?;
    let body = read_obj(dir.join("defur/root_mesh.obj"))?;
    if learned.is_empty() {
        return Err(format!("{learner}/strands.hair has no strands").into());
    }
    let l = learned.strand(0).len();
    // Colours modelled and fitted as the learner did.
    let trained: LearnMetrics = read_json(dir.join(format!("{learner}/metrics.json")))?;
    let cfg = LearnParams::defaults()?.image_config(Renderer::Cpu, trained.colors);
    for k in ks {
        let widths: Vec<f32> = learned.width.iter().map(|w| w * k).collect();
        let mut img = ImageLosses::new(&views, None, &body, widths.clone(), &cfg)?;
        img.fit_colors(&learned.points, l, Formation::Training, ColorFitPass::Start)?;
        img.fit_colors(&learned.points, l, Formation::HeldOut, ColorFitPass::Final)?;
        let mut strands = Strands::new();
        for (s, c) in img.colors().iter().enumerate() {
            strands.push(learned.strand(s), learned.part[s], widths[s], *c);
        }
        let tmp = tempfile::tempdir()?;
        img.render_test_views(&strands, tmp.path())?;
        let (psnr, ssim, n) = image_metrics(tmp.path(), &views, [0.0; 3])?;
        println!(
            "{learner} strands, widths x {k}: PSNR {psnr:.2} dB, SSIM {ssim:.3} over {n} held-out views"
        );
        println!(
            "  {}",
            common::OutlineError::measure(tmp.path(), &views)?.describe()
        );
    }
    Ok(())
}
