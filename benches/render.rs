//! Benchmark of the CPU Gaussian renderer (`cargo bench --bench render`).
//!
//! Scenes are synthetic fur: strands of 8 segments grown outward (with a
//! random lean) from roots on a unit sphere, one Gaussian per segment, seen
//! from a camera 3.2 units away with a 50-degree-ish field of view, so the
//! whole ball fills most of the image. For every resolution (128^2, 256^2,
//! 512^2) and segment count (10k, 100k, 1M) it times the forward pass and
//! forward + backward (an L1 photometric gradient on RGB plus alpha), median
//! of several runs, and prints milliseconds and Gaussian-pixel evaluations
//! per second (evaluations counted by the forward pass). It then times the
//! issue's target case (256^2, 200k segments, forward + backward <= 0.5 s)
//! and writes every record as JSON to `target/bench/render.json`. Every
//! record also times a colour fit's per-view sums both ways
//! (`render::blend_sums`, one compositing pass, against the render and two
//! backward passes it replaces, `Renderer::blend_sums_by_backward`) and
//! gives their ratio.
//!
//! Environment: `FURE_BENCH_QUICK=1` runs only the target case;
//! `RAYON_NUM_THREADS` sets the thread count.

use std::time::Instant;

use fure_stages::data::image::ImageF32;
use fure_stages::render::device::Renderer;
use fure_stages::render::{backward, blend_sums, render, OutputGrads, RenderSettings, Vec3};

mod common;
#[path = "common/scene.rs"]
mod scene;
use scene::{camera, fur_ball};

/// CPU time (user + system, all threads) of this process in milliseconds,
/// from /proc/self/stat (clock ticks, usually 10 ms); None elsewhere.
fn cpu_ms() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks * 10.0)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

struct Record {
    size: u32,
    segments: usize,
    instances: usize,
    evaluations: u64,
    forward_ms: f64,
    forward_backward_ms: f64,
    /// Mean CPU time of one forward + backward (all threads).
    cpu_ms: Option<f64>,
    /// A colour fit's sums for the view: one compositing pass, and a render
    /// with two backward passes.
    blend_sums_ms: f64,
    blend_sums_by_backward_ms: f64,
}

fn bench(size: u32, segments: usize) -> Record {
    let g = fur_ball(segments, 1234 + segments as u64);
    let cam = camera(size);
    let s = RenderSettings {
        background: Vec3::splat(1.0),
        ..Default::default()
    };
    // Warm-up and the loss gradient (L1 towards a flat grey target).
    let (out, st) = render(&g, &cam, &s).expect("render");
    let mut grgb = ImageF32::new(size, size, 3);
    for (gv, v) in grgb.data.iter_mut().zip(&out.rgb.data) {
        *gv = if *v > 0.5 { 1.0 } else { -1.0 } / (3 * size * size) as f32;
    }
    let mut galpha = ImageF32::new(size, size, 1);
    for (gv, v) in galpha.data.iter_mut().zip(&out.alpha.data) {
        *gv = if *v > 0.5 { -1.0 } else { 1.0 } / (size * size) as f32;
    }
    let dl = OutputGrads {
        rgb: Some(grgb),
        alpha: Some(galpha),
        ..Default::default()
    };
    let reps = if segments >= 1_000_000 { 3 } else { 5 };
    let mut fwd = Vec::new();
    let mut both = Vec::new();
    let cpu0 = cpu_ms();
    for _ in 0..reps {
        let t0 = Instant::now();
        let (o, st2) = render(&g, &cam, &s).expect("render");
        let t1 = Instant::now();
        let gr = backward(&g, &cam, &s, &st2, &dl).expect("backward");
        let t2 = Instant::now();
        std::hint::black_box((&o, &gr));
        fwd.push((t1 - t0).as_secs_f64() * 1e3);
        both.push((t2 - t0).as_secs_f64() * 1e3);
    }
    let cpu = cpu0.zip(cpu_ms()).map(|(a, b)| (b - a) / reps as f64);
    let target = out.rgb.clone();
    let mut weight = ImageF32::new(size, size, 1);
    weight.data.fill(1.0);
    let mut one_pass = Vec::new();
    let mut by_backward = Vec::new();
    for _ in 0..reps {
        let t0 = Instant::now();
        let a = blend_sums(&g, &cam, &s, &target, &weight).expect("blend_sums");
        let t1 = Instant::now();
        let b = Renderer::Cpu
            .blend_sums_by_backward(&g, &cam, &s, &target, &weight)
            .expect("blend_sums_by_backward");
        let t2 = Instant::now();
        std::hint::black_box((&a, &b));
        one_pass.push((t1 - t0).as_secs_f64() * 1e3);
        by_backward.push((t2 - t1).as_secs_f64() * 1e3);
    }
    Record {
        blend_sums_ms: median(one_pass),
        blend_sums_by_backward_ms: median(by_backward),
        cpu_ms: cpu,
        size,
        segments: g.len(),
        instances: st.instance_count(),
        evaluations: st.evaluations,
        forward_ms: median(fwd),
        forward_backward_ms: median(both),
    }
}

fn print(r: &Record) {
    println!(
        "{:>4}^2 {:>8} segs  {:>9} inst  fwd {:>8.1} ms  fwd+bwd {:>8.1} ms (cpu {:>8.1} ms)  {:>6.1} M Gaussian-px evals/s (fwd)  colour-fit sums {:>7.1} ms (render + 2 bwd {:>7.1} ms, {:.1}x)",
        r.size,
        r.segments,
        r.instances,
        r.forward_ms,
        r.forward_backward_ms,
        r.cpu_ms.unwrap_or(f64::NAN),
        r.evaluations as f64 / (r.forward_ms * 1e-3) / 1e6,
        r.blend_sums_ms,
        r.blend_sums_by_backward_ms,
        r.blend_sums_by_backward_ms / r.blend_sums_ms
    );
}

fn main() {
    let quick = std::env::var("FURE_BENCH_QUICK").is_ok_and(|v| v == "1");
    let threads = rayon::current_num_threads();
    println!("render benchmark: {threads} rayon threads, median of runs");
    let mut records = Vec::new();
    if !quick {
        for size in [128u32, 256, 512] {
            for segments in [10_000usize, 100_000, 1_000_000] {
                let r = bench(size, segments);
                print(&r);
                records.push(r);
            }
        }
    }
    let target = bench(256, 200_000);
    print(&target);
    println!(
        "target (256^2, 200k segments, fwd+bwd <= 500 ms): {:.1} ms -> {}",
        target.forward_backward_ms,
        if target.forward_backward_ms <= 500.0 {
            "met"
        } else {
            "NOT met"
        }
    );
    records.push(target);
    let json: Vec<serde_json::Value> = records
        .iter()
        .map(|r| {
            serde_json::json!({
                "size": r.size,
                "segments": r.segments,
                "instances": r.instances,
                "evaluations": r.evaluations,
                "forward_ms": r.forward_ms,
                "forward_backward_ms": r.forward_backward_ms,
                "forward_backward_cpu_ms": r.cpu_ms,
                "evaluations_per_s": r.evaluations as f64 / (r.forward_ms * 1e-3),
                "blend_sums_ms": r.blend_sums_ms,
                "blend_sums_by_backward_ms": r.blend_sums_by_backward_ms,
                "blend_sums_speedup": r.blend_sums_by_backward_ms / r.blend_sums_ms,
            })
        })
        .collect();
    let dir = std::path::Path::new(
        &std::env::var("CARGO_TARGET_DIR").unwrap_or_else(|_| "target".into()),
    )
    .join("bench");
    let doc = serde_json::json!({ "threads": threads, "records": json });
    match std::fs::create_dir_all(&dir).and_then(|_| {
        std::fs::write(
            dir.join("render.json"),
            serde_json::to_string_pretty(&doc).unwrap_or_default(),
        )
    }) {
        Ok(()) => println!("wrote {}", dir.join("render.json").display()),
        Err(e) => eprintln!("could not write {}: {e}", dir.display()),
    }
}
