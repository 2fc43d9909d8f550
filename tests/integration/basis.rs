//! The strand basis from a user's PERM file end to end: a synthetic
//! `fft-strands-blend-shapes.npz` in PERM's exact layout (`mean_shape`
//! (1, 50, 6) and `blend_shapes` (K, 50, 6), float32, one entry deflated as
//! `np.savez_compressed` writes it) through the `perm` input of `strand_basis`,
//! codec training and evaluation on the tiny tiger; and a malformed file
//! refused naming the file and the array.

use std::path::Path;

use crate::engine::Project;
use crate::method::tiny_pipeline;

/// PERM's frequency bins (50) and decoded samples (99, a zero root prepended).
const BINS: usize = 50;
const SAMPLES: usize = 2 * (BINS - 1) + 1;

/// Forward real FFT with orthonormal scaling (numpy's `rfft(x, norm="ortho")`), the first `BINS` bins.
fn rfft_ortho(x: &[f64]) -> Vec<(f64, f64)> {
    let n = x.len() as f64;
    (0..BINS)
        .map(|k| {
            let (mut re, mut im) = (0.0, 0.0);
            for (t, v) in x.iter().enumerate() {
                let a = -2.0 * std::f64::consts::PI * (k * t) as f64 / n;
                re += v * a.cos();
                im += v * a.sin();
            }
            (re / n.sqrt(), im / n.sqrt())
        })
        .collect()
}

/// PERM's feature block of one strand given as 99 points (head frame, cm): per bin the real parts
/// of x, y, z then the imaginary parts.
fn features(points: &[[f64; 3]]) -> Vec<f32> {
    let mut f = vec![0f32; BINS * 6];
    for c in 0..3 {
        let signal: Vec<f64> = points.iter().map(|p| p[c]).collect();
        for (i, (re, im)) in rfft_ortho(&signal).into_iter().enumerate() {
            f[i * 6 + c] = re as f32;
            f[i * 6 + 3 + c] = im as f32;
        }
    }
    f
}

/// A PERM-layout npz: a mean strand falling down the back of the head (PERM -y, bending toward
/// -z) and `k` blend shapes of lateral and outward sways, in centimetres; `bins` frequency bins of
/// the blend shapes (PERM: 50).
fn perm_npz(path: &Path, k: usize, shape_bins: usize) {
    let t = |i: usize| (i + 1) as f64 / SAMPLES as f64;
    let mean: Vec<[f64; 3]> = (0..SAMPLES)
        .map(|i| {
            let s = t(i);
            [0.0, -20.0 * s, -4.0 * s * s]
        })
        .collect();
    let mut blend = Vec::new();
    for c in 0..k {
        let f = (c / 2 + 1) as f64;
        let pts: Vec<[f64; 3]> = (0..SAMPLES)
            .map(|i| {
                let w = (std::f64::consts::PI * f * t(i)).sin() * t(i);
                if c % 2 == 0 {
                    [w, 0.0, 0.0]
                } else {
                    [0.0, 0.0, -w]
                }
            })
            .collect();
        let mut fb = features(&pts);
        fb.truncate(shape_bins * 6);
        fb.resize(shape_bins * 6, 0.0);
        blend.extend(fb);
    }
    let bytes = fure_stages::growth::strand_basis::npz_bytes(&[
        ("mean_shape", &[1, BINS, 6], &features(&mean), false),
        ("blend_shapes", &[k, shape_bins, 6], &blend, true),
    ]);
    std::fs::write(path, bytes).unwrap();
}

/// `tiny_pipeline()` with the basis decoded from `perm.npz` next to it.
fn perm_pipeline() -> String {
    format!(
        "{}\n[stages.basis]\ninputs = {{ perm = \"perm.npz\" }}\n",
        tiny_pipeline()
    )
}

fn read_json(path: &Path) -> serde_json::Value {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn a_perm_npz_runs_through_codec_training_to_evaluation() {
    let p = Project::new();
    p.write("tiny.toml", &perm_pipeline());
    perm_npz(&p.path("perm.npz"), 6, BINS);
    let r = p.run("tiny.toml", &["--until", "evaluate"]);
    r.ok();
    for stage in ["basis", "codec", "evaluate"] {
        assert_eq!(r.status(stage), "ran", "{stage}: {:?}", r.stages);
    }
    let out = p.path("out/tiny");

    // The basis came from PERM: all 6 blend shapes, the automatic 8 points, unit length.
    let m = read_json(&out.join("basis/metrics.json"));
    assert_eq!(m["source"], "perm", "{m}");
    assert_eq!(m["k"], 6, "{m}");
    assert_eq!(m["points"], 8, "{m}");
    let basis: fure_stages::growth::strand_basis::StrandBasis =
        serde_json::from_value(read_json(&out.join("basis/basis.json"))).unwrap();
    basis.validate("basis.json").unwrap();
    let arc: f32 = basis.mean.windows(2).map(|w| (w[1] - w[0]).length()).sum();
    assert!((arc - 1.0).abs() < 0.02, "mean arc length {arc}");
    // Falling down the head (PERM -y) is our tangent direction x.
    assert!(basis.mean[7].x > 0.9, "{:?}", basis.mean);
    // Hair on a head lies along it, so the basis carries the fur corpus' elevation for where
    // the views' is not trusted, and the codec's start reports it as its fallback.
    let fallback = basis
        .untrusted_elevation_deg
        .expect("a PERM basis' fallback elevation");
    assert!(
        basis.mean_elevation().to_degrees() < 15.0,
        "{:?}",
        basis.mean
    );
    assert!(fallback > 25.0, "{fallback}");
    assert_eq!(
        m["untrusted_elevation_deg"].as_f64(),
        Some(fallback as f64),
        "{m}"
    );
    let codec = read_json(&out.join("codec/metrics.json"));
    let used = codec["view_elevation"]["fallback_deg"]
        .as_f64()
        .unwrap_or(f64::NAN);
    assert!(
        (used - fallback as f64).abs() < 1e-3,
        "{}",
        codec["view_elevation"]
    );

    // The codec trained on it and wrote finite strands that the evaluation scored.
    let strands =
        fure_stages::evaluation::evaluate::read_strands_any(&out.join("codec/strands.hair"))
            .unwrap();
    assert!(!strands.is_empty());
    assert!(strands.points.iter().all(|p| p.is_finite()));
    let eval = read_json(&out.join("evaluate/metrics.json"));
    for t in ["2cm_20deg", "3cm_30deg", "4cm_40deg"] {
        let f = eval["prf_signed"][t]["fscore"].as_f64().unwrap_or(f64::NAN);
        assert!((0.0..=100.0).contains(&f), "prf_signed.{t}.fscore = {f}");
    }
}

#[test]
fn a_malformed_perm_npz_is_refused_naming_the_file_and_the_array() {
    let p = Project::new();
    p.write("tiny.toml", &perm_pipeline());
    // 49 frequency bins in the blend shapes against the mean's 50.
    perm_npz(&p.path("perm.npz"), 3, BINS - 1);
    let r = p.run("tiny.toml", &["--until", "basis"]);
    assert_ne!(r.code(), 0, "{}", r.stdout());
    assert_eq!(r.status("basis"), "failed", "{:?}", r.stages);
    let text = format!("{}{}", r.stdout(), r.stderr());
    assert!(
        text.contains("perm.npz") && text.contains("`blend_shapes` has shape [3, 49, 6]"),
        "{text}"
    );
    assert!(text.contains("expected (K, 50, 6)"), "{text}");
}
