//! GPU against CPU renderer: forward + backward timings
//! (`cargo bench --features gpu --bench gpu`).
//!
//! The scenes are `render.rs`'s fur balls (strands of 8 segments on a unit
//! sphere, one Gaussian per segment, an L1 RGB + alpha loss gradient). Cases:
//! 256^2 with 200k segments and 1024^2 with 1M segments. For each it prints
//! the median forward and forward + backward time on the CPU reference and on
//! the GPU (deterministic mode, and the atomic mode's forward + backward), the
//! CPU/GPU ratio, the largest image difference, and the adapter's name.
//! The GPU time includes the upload of the Gaussians, the readback of the
//! images and of the gradients: what a learner pays per view.
//!
//! Environment: `FURE_BENCH_GPU_CASES=128x20000,256x200000` replaces the
//! cases (SIZExSEGMENTS; lavapipe, the software adapter, is slow for the big
//! ones); `FURE_BENCH_REPS` sets the timed runs (default 3);
//! `FURE_BENCH_JSON=path` writes the records as JSON there;
//! `FURE_GPU_ADAPTER=substring` picks the adapter by name.
//!
//! Then one photometric step (render, `(1 - 0.2) L1 + 0.2 D-SSIM` on the
//! colour plus a silhouette L1, backward: a `frosting` iteration) three
//! ways: the CPU's, the GPU's with the losses on the host (images read back,
//! SSIM on the device, gradients uploaded) and the GPU's fused step (images
//! stay on the device).
//!
//! And the colour fits' per-Gaussian blend sums three ways: the CPU's one
//! compositing pass, the GPU's `blend` kernels, and the GPU's render + two
//! backward passes.
//!
//! After the timed runs, the same calls run once more per repetition with
//! [`GpuRenderer::set_profiling`] on, and the time per phase (upload, each
//! kernel group, readbacks, host packing) is printed and recorded under
//! `gpu_phases`.

use std::time::Instant;

use fure_stages::data::image::ImageF32;
use std::sync::Arc;

use fure_stages::render::device::{ImageLoss, Renderer, ViewTargets};
use fure_stages::render::gpu::{GpuMode, GpuRenderer};
use fure_stages::render::{backward, render, OutputGrads, RenderSettings, Vec3};

mod common;
#[path = "common/scene.rs"]
mod scene;
use scene::{camera, fur_ball};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn loss_grads(out: &fure_stages::render::RenderOutput, size: u32) -> OutputGrads {
    let mut grgb = ImageF32::new(size, size, 3);
    for (gv, v) in grgb.data.iter_mut().zip(&out.rgb.data) {
        *gv = if *v > 0.5 { 1.0 } else { -1.0 } / (3 * size * size) as f32;
    }
    let mut galpha = ImageF32::new(size, size, 1);
    for (gv, v) in galpha.data.iter_mut().zip(&out.alpha.data) {
        *gv = if *v > 0.5 { -1.0 } else { 1.0 } / (size * size) as f32;
    }
    OutputGrads {
        rgb: Some(grgb),
        alpha: Some(galpha),
        ..Default::default()
    }
}

/// Median milliseconds of `reps` photometric steps per device way (see the
/// module doc): (cpu, gpu with host losses, gpu fused).
fn photometric_steps(
    gpu: &Arc<GpuRenderer>,
    g: &fure_stages::render::Gaussians,
    cam: &fure_stages::data::camera::Camera,
    s: &RenderSettings,
    out: &fure_stages::render::RenderOutput,
    reps: usize,
) -> (f64, f64, f64) {
    let target = ImageF32 {
        data: out.rgb.data.iter().map(|v| 1.0 - v).collect(),
        ..out.rgb.clone()
    };
    let mask = ImageF32 {
        data: out
            .alpha
            .data
            .iter()
            .map(|v| (*v > 0.5) as u8 as f32)
            .collect(),
        ..out.alpha.clone()
    };
    let terms = ImageLoss {
        lambda_dssim: 0.2,
        rgb: 1.0,
        silhouette: 0.5,
        fur: 0.0,
        orientation: 0.0,
    };
    let dev = Renderer::Gpu(gpu.clone());
    let t = ViewTargets {
        rgb: &target,
        mask: Some(&mask),
        fur: None,
        orientation: None,
        region: None,
    };
    let resident = dev.resident_target(&t).expect("gpu target");
    let ways = [
        (&Renderer::Cpu, None),
        (&dev, None),
        (&dev, resident.as_ref()),
    ];
    let mut med = [0.0; 3];
    for (m, (r, res)) in med.iter_mut().zip(ways) {
        r.image_step(g, cam, s, &t, res, &terms)
            .expect("warm-up step");
        let mut v = Vec::new();
        for _ in 0..reps {
            let t0 = Instant::now();
            std::hint::black_box(r.image_step(g, cam, s, &t, res, &terms).expect("step"));
            v.push(ms(t0));
        }
        *m = median(v);
    }
    (med[0], med[1], med[2])
}

/// The colour fits' blend sums (`Renderer::blend_sums`, target = the CPU's
/// render, pixel weight 1) three ways: the CPU's one compositing pass, the
/// GPU's `blend` kernels, and the GPU's render + two backward passes (how
/// the GPU took them before). Returns the three medians (ms) and the
/// largest |gpu - cpu| difference with the largest |cpu| sum.
fn blend_sums_timings(
    gpu: &Arc<GpuRenderer>,
    g: &fure_stages::render::Gaussians,
    cam: &fure_stages::data::camera::Camera,
    s: &RenderSettings,
    out: &fure_stages::render::RenderOutput,
    reps: usize,
) -> ([f64; 3], f32, f32) {
    let cpu = Renderer::Cpu;
    let dev = Renderer::Gpu(gpu.clone());
    let mut weight = ImageF32::new(out.rgb.width, out.rgb.height, 1);
    weight.data.fill(1.0);
    let target = &out.rgb;
    let reference = cpu
        .blend_sums(g, cam, s, target, &weight)
        .expect("cpu sums");
    let on_gpu = dev
        .blend_sums(g, cam, s, target, &weight)
        .expect("gpu sums");
    let scale = reference
        .iter()
        .flatten()
        .fold(0.0f32, |m, v| m.max(v.abs()));
    let diff = reference
        .iter()
        .flatten()
        .zip(on_gpu.iter().flatten())
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    let mut med = [0.0; 3];
    for (way, m) in med.iter_mut().enumerate() {
        let mut v = Vec::new();
        for _ in 0..reps {
            let t0 = Instant::now();
            let sums = match way {
                0 => cpu.blend_sums(g, cam, s, target, &weight),
                1 => dev.blend_sums(g, cam, s, target, &weight),
                _ => dev.blend_sums_by_backward(g, cam, s, target, &weight),
            };
            std::hint::black_box(sums.expect("blend sums"));
            v.push(ms(t0));
        }
        *m = median(v);
    }
    (med, diff, scale)
}

fn bench(
    gpu: &Arc<GpuRenderer>,
    atomic: &GpuRenderer,
    size: u32,
    segments: usize,
    reps: usize,
) -> serde_json::Value {
    let g = fur_ball(segments, 1234 + segments as u64);
    let cam = camera(size);
    let s = RenderSettings {
        background: Vec3::splat(1.0),
        ..Default::default()
    };
    let (out, st) = render(&g, &cam, &s).expect("cpu render");
    let dl = loss_grads(&out, size);
    let (cf, mut cb) = (Vec::new(), Vec::new());
    let mut cf = cf;
    for _ in 0..reps {
        let t0 = Instant::now();
        let (o, st2) = render(&g, &cam, &s).expect("cpu render");
        cf.push(ms(t0));
        let gr = backward(&g, &cam, &s, &st2, &dl).expect("cpu backward");
        cb.push(ms(t0));
        std::hint::black_box((&o, &gr));
    }
    let cpu_grads = backward(&g, &cam, &s, &st, &dl).expect("cpu backward");
    // GPU: one warm-up (pipeline caches, allocations), then timed runs.
    let (go, gst) = gpu.render(&g, &cam, &s).expect("gpu render");
    let gg = gpu.backward(&g, &cam, &s, &gst, &dl).expect("gpu backward");
    let max_img = out
        .rgb
        .data
        .iter()
        .zip(&go.rgb.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let scale = cpu_grads
        .means
        .iter()
        .fold(0.0f32, |m, v| m.max(v.abs().max_element()));
    let dmax = cpu_grads
        .means
        .iter()
        .zip(&gg.means)
        .fold(0.0f32, |m, (a, b)| m.max((*a - *b).abs().max_element()));
    let (mut gf, mut gb, mut ab) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..reps {
        let t0 = Instant::now();
        let (o, st2) = gpu.render(&g, &cam, &s).expect("gpu render");
        gf.push(ms(t0));
        let gr = gpu.backward(&g, &cam, &s, &st2, &dl).expect("gpu backward");
        gb.push(ms(t0));
        std::hint::black_box((&o, &gr));
        let t0 = Instant::now();
        let (o, st2) = atomic.render(&g, &cam, &s).expect("gpu render");
        let gr = atomic
            .backward(&g, &cam, &s, &st2, &dl)
            .expect("gpu backward");
        ab.push(ms(t0));
        std::hint::black_box((&o, &gr));
    }
    // Where the deterministic mode's time goes: each phase waited for on its own.
    gpu.set_profiling(true);
    for _ in 0..reps {
        let (o, st2) = gpu.render(&g, &cam, &s).expect("gpu render");
        let gr = gpu.backward(&g, &cam, &s, &st2, &dl).expect("gpu backward");
        std::hint::black_box((&o, &gr));
    }
    let profile = gpu.profile();
    gpu.set_profiling(false);
    let phases: Vec<serde_json::Value> = profile
        .phases
        .iter()
        .map(|(name, total, calls)| {
            let per_call = total / *calls as f64;
            println!("    {name:<36} {per_call:>9.2} ms");
            serde_json::json!({"phase": name, "ms_per_call": per_call})
        })
        .collect();
    let (cf, cb, gf, gb, ab) = (median(cf), median(cb), median(gf), median(gb), median(ab));
    let (sc, sh, sf) = photometric_steps(gpu, &g, &cam, &s, &out, reps);
    println!(
        "{size:>4}^2 photometric step | cpu {sc:>8.1} ms | gpu, losses on the host {sh:>8.1} ms | \
         gpu fused {sf:>8.1} ms | cpu/gpu fused {:>6.2}x",
        sc / sf
    );
    let ([bc, bg, bb], bdiff, bscale) = blend_sums_timings(gpu, &g, &cam, &s, &out, reps);
    println!(
        "{size:>4}^2 blend sums | cpu {bc:>8.1} ms | gpu kernels {bg:>8.1} ms | gpu render + 2 backward \
         {bb:>8.1} ms | cpu/gpu {:>6.2}x | max |gpu - cpu| {bdiff:.1e} of {bscale:.1e}",
        bc / bg
    );
    println!(
        "{size:>4}^2 {:>8} segs {:>9} inst | cpu fwd {cf:>8.1} ms fwd+bwd {cb:>8.1} ms | gpu fwd {gf:>8.1} ms \
         fwd+bwd {gb:>8.1} ms (atomic {ab:>8.1} ms) | cpu/gpu fwd+bwd {:>6.2}x | max |rgb diff| {max_img:.1e}, \
         max |dmean diff| {:.1e} of {scale:.1e}",
        g.len(),
        st.instance_count(),
        cb / gb,
        dmax
    );
    serde_json::json!({
        "size": size,
        "segments": g.len(),
        "instances": st.instance_count(),
        "gpu_instances": gst.instance_count(),
        "evaluations": st.evaluations,
        "cpu_forward_ms": cf,
        "cpu_forward_backward_ms": cb,
        "gpu_forward_ms": gf,
        "gpu_forward_backward_ms": gb,
        "gpu_atomic_forward_backward_ms": ab,
        "cpu_over_gpu_forward_backward": cb / gb,
        "max_abs_rgb_difference": max_img,
        "max_abs_mean_gradient_difference": dmax,
        "max_abs_mean_gradient": scale,
        "gpu_phases": phases,
        "step_cpu_ms": sc,
        "step_gpu_host_losses_ms": sh,
        "step_gpu_fused_ms": sf,
        "cpu_over_gpu_fused_step": sc / sf,
        "blend_sums_cpu_ms": bc,
        "blend_sums_gpu_ms": bg,
        "blend_sums_gpu_by_backward_ms": bb,
        "blend_sums_max_abs_difference": bdiff,
        "blend_sums_max_abs": bscale,
    })
}

fn main() {
    let gpu = match GpuRenderer::new(GpuMode::Deterministic) {
        Ok(r) => Arc::new(r),
        Err(e) => {
            println!("gpu benchmark SKIPPED: {e}");
            return;
        }
    };
    let atomic = GpuRenderer::new(GpuMode::Atomic).expect("second device");
    let adapter = gpu.adapter_description();
    let threads = rayon::current_num_threads();
    println!("gpu benchmark: adapter {adapter}; cpu: {threads} rayon threads; median of runs");
    let cases: Vec<(u32, usize)> = match std::env::var("FURE_BENCH_GPU_CASES") {
        Ok(v) => v
            .split(',')
            .map(|c| {
                let (a, b) = c.trim().split_once('x').expect("SIZExSEGMENTS");
                (a.parse().expect("size"), b.parse().expect("segments"))
            })
            .collect(),
        Err(_) => vec![(256, 200_000), (1024, 1_000_000)],
    };
    let reps: usize = std::env::var("FURE_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3)
        .max(1);
    let records: Vec<serde_json::Value> = cases
        .iter()
        .map(|&(size, segs)| bench(&gpu, &atomic, size, segs, reps))
        .collect();
    if let Ok(path) = std::env::var("FURE_BENCH_JSON") {
        let doc = serde_json::json!({
            "bench": "gpu",
            "adapter": gpu.adapter_name(),
            "adapter_description": adapter,
            "cpu_threads": threads,
            "reps": reps,
            "records": records,
        });
        let text = serde_json::to_string_pretty(&doc).expect("json");
        std::fs::write(&path, text + "\n").expect("write FURE_BENCH_JSON");
        println!("wrote {path}");
    }
}
