//! The fur method end to end through the `fure` binary, on the quickest
//! synthetic tiger: `pipelines/tiger.toml` itself (extended with small sizes,
//! so the DAG under test is the shipped one), its cache behaviour when only a
//! strand-learning parameter changes, byte-for-byte determinism across fresh
//! caches, `pipelines/speed_accuracy.toml` on the same cache (the ablations
//! and the dense baseline reuse the tiger's defurring), and
//! `pipelines/capture.toml` on a capture without ground truth.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use serde_json::Value as Json;

use crate::engine::Project;

fn repo(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

/// `tiger.toml` at its smallest: 8 views of 64 px, a small Gaussian fit, few
/// roots and learning iterations. About 5 s in release.
pub(crate) fn tiny_pipeline() -> String {
    tiny_extension("pipelines/tiger.toml", "tiny")
}

/// `pipeline` (a shipped file) extended with the smallest sizes of
/// [`tiny_pipeline`], under the name `name`: the stages it shares with
/// `tiger.toml` get the same parameters, hence the same cache keys.
fn tiny_extension(pipeline: &str, name: &str) -> String {
    format!(
        r#"extends = '{}'

[pipeline]
name = "{name}"

[stages.scene]
size = "quick"
views = 8
test_views = 1
resolution = 64
supersample = 1

[stages.frosting]
gaussians = 1500
iterations = 40

[stages.roots]
roots_per_pixel = 1.0

[stages.codec]
iterations = 10
"#,
        repo(pipeline).display()
    )
}

/// `tiger.toml` at its shipped size under the name `name`, with `extra` TOML appended.
fn tiger_as(name: &str, extra: &str) -> String {
    format!(
        "extends = '{}'\n\n[pipeline]\nname = \"{name}\"\n\n{extra}",
        repo("pipelines/tiger.toml").display()
    )
}

/// Every regular file under `dir`, relative to it, sorted.
fn files(dir: &Path) -> BTreeSet<PathBuf> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeSet<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.insert(p.strip_prefix(root).unwrap().to_path_buf());
            }
        }
    }
    let mut out = BTreeSet::new();
    walk(dir, dir, &mut out);
    out
}

/// A JSON value without the keys that hold wall-clock measurements.
fn without_timings(v: Json) -> Json {
    match v {
        Json::Object(m) => Json::Object(
            m.into_iter()
                .filter(|(k, _)| !k.contains("second"))
                .map(|(k, v)| (k, without_timings(v)))
                .collect(),
        ),
        Json::Array(a) => Json::Array(a.into_iter().map(without_timings).collect()),
        v => v,
    }
}

fn read_json(path: &Path) -> Json {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `v[key]` as a finite number.
fn number(v: &Json, key: &str, file: &str) -> f64 {
    let x = v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{file}: `{key}` is not a number: {}", v[key]));
    assert!(x.is_finite(), "{file}: `{key}` = {x}");
    x
}

const TIGER_STAGES: [&str; 13] = [
    "basis",
    "codec",
    "defur",
    "defur_baseline",
    "evaluate",
    "frosting",
    "groom",
    "lengths",
    "orientation",
    "outer",
    "parts",
    "roots",
    "scene",
];

#[test]
fn tiger_pipeline_runs_end_to_end_deterministically_and_reruns_only_learning() {
    // Two projects with their own caches, run side by side.
    let (a, b) = (Project::new(), Project::new());
    for p in [&a, &b] {
        p.write("tiny.toml", &tiny_pipeline());
    }
    let (ra, rb) = std::thread::scope(|s| {
        let ha = s.spawn(|| a.run("tiny.toml", &[]));
        let hb = s.spawn(|| b.run("tiny.toml", &[]));
        (ha.join().unwrap(), hb.join().unwrap())
    });
    for r in [&ra, &rb] {
        r.ok();
        assert_eq!(r.with("ran"), TIGER_STAGES, "{:?}", r.stages);
    }

    // The metrics the issues promise, as finite numbers.
    let out = a.path("out/tiny");
    let eval = read_json(&out.join("evaluate/metrics.json"));
    for table in ["prf", "prf_signed"] {
        for t in ["2cm_20deg", "3cm_30deg", "4cm_40deg"] {
            for m in ["precision", "recall", "fscore"] {
                let x = number(&eval[table][t], m, "evaluate/metrics.json");
                assert!((0.0..=100.0).contains(&x), "{table}.{t}.{m} = {x}");
            }
        }
    }
    let defur = read_json(&out.join("defur/metrics.json"));
    let promised: [(&Json, &str, &[&str]); 2] = [
        (
            &eval,
            "evaluate/metrics.json",
            &[
                "mean_length_cm",
                "std_length_cm",
                "psnr",
                "ssim",
                "train_seconds",
            ],
        ),
        (
            &defur,
            "defur/metrics.json",
            &[
                "root_to_skin_mean_cm",
                "root_to_skin_p95_cm",
                "root_to_skin_mean_frac",
                "outer_to_skin_mean_frac",
                "baseline_to_skin_mean_frac",
                "seconds_solve",
            ],
        ),
    ];
    for (metrics, file, keys) in promised {
        for k in keys {
            number(metrics, k, file);
        }
    }
    let lengths = read_json(&out.join("lengths/metrics.json"));
    let errors = lengths["length_error_pct"]
        .as_object()
        .expect("lengths/metrics.json: length_error_pct");
    assert!(errors.contains_key("torso"), "{errors:?}");
    for (part, e) in errors {
        assert!(e.as_f64().is_some_and(f64::is_finite), "{part}: {e}");
    }

    // Same inputs and seeds, fresh caches: the same bytes everywhere except
    // wall-clock fields, the scene's timing report (nothing else) and the
    // learner's snapshots, which are taken at wall-clock times by design.
    let out_b = b.path("out/tiny");
    let timed =
        |f: &PathBuf| f.starts_with("codec/snapshots") || f == Path::new("scene/report.json");
    let fa: BTreeSet<PathBuf> = files(&out).into_iter().filter(|f| !timed(f)).collect();
    let fb: BTreeSet<PathBuf> = files(&out_b).into_iter().filter(|f| !timed(f)).collect();
    assert_eq!(fa, fb, "the two runs wrote different files");
    assert!(fa.contains(Path::new("codec/strands.hair")), "{fa:?}");
    for f in &fa {
        let (x, y) = (out.join(f), out_b.join(f));
        if f.extension().is_some_and(|e| e == "json") {
            assert_eq!(
                without_timings(read_json(&x)),
                without_timings(read_json(&y)),
                "{} differs between two fresh runs",
                f.display()
            );
        } else {
            assert!(
                std::fs::read(&x).unwrap() == std::fs::read(&y).unwrap(),
                "{} differs between two fresh runs",
                f.display()
            );
        }
    }

    // A strand-learning parameter reruns the learner, its evaluation and the groom export only.
    let r = a.run("tiny.toml", &["--set", "codec.iterations=4"]);
    r.ok();
    assert_eq!(
        r.with("ran"),
        ["codec", "evaluate", "groom"],
        "{:?}",
        r.stages
    );
    assert_eq!(r.with("cached").len(), TIGER_STAGES.len() - 3);
}

#[test]
fn capture_pipeline_runs_on_a_capture_without_ground_truth() {
    let p = Project::new();
    p.write("tiny.toml", &tiny_pipeline());
    p.run("tiny.toml", &["--until", "scene"]).ok();
    write_capture(&p, "cap", 1.0);
    let gt = read_json(&p.path("out/tiny/scene/scene.json"));

    let r = p.run("cap/capture.toml", &TINY_CAPTURE);
    r.ok();
    assert_eq!(r.with("failed"), Vec::<&str>::new());
    let out = p.path("out/capture");
    let strands = std::fs::metadata(out.join("codec/strands.hair")).expect("strands.hair");
    assert!(strands.len() > 1000, "{} bytes", strands.len());
    assert!(out.join("defur/root_mesh.obj").is_file());
    for f in ["groom/blender.py", "groom/groom.usda"] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // No ground truth was given, so no ground-truth metrics were invented.
    let defur = read_json(&out.join("defur/metrics.json"));
    assert!(defur.get("root_to_skin_mean_cm").is_none(), "{defur}");
    let lengths = read_json(&out.join("lengths/metrics.json"));
    assert!(lengths.get("length_error_pct").is_none(), "{lengths}");
    // The metric scale came from the eyes, not from the (ignored) s_cm = 1.
    let s_cm = number(&lengths, "s_cm", "lengths/metrics.json");
    let s_gt = gt["s_cm"].as_f64().unwrap();
    assert!(
        (s_cm - s_gt).abs() < 0.01 * s_gt,
        "s_cm {s_cm}, truth {s_gt}"
    );
}

/// Copies the tiny scene (`out/tiny/scene`, already run) into `dir` as a
/// user's capture (views, eyes, a labelled mesh; no ground truth), with every
/// length multiplied by `scale` (camera positions, the mesh, the eyes): 100
/// turns a capture in metres into the same capture in centimetres.
fn write_capture(p: &Project, dir: &str, scale: f64) {
    let scene = p.path("out/tiny/scene");
    for f in files(&scene.join("views")) {
        let src = scene.join("views").join(&f);
        let dst = p.path(dir).join("views").join(&f);
        std::fs::create_dir_all(dst.parent().unwrap()).unwrap();
        if f.extension().is_some_and(|e| e == "json") {
            let mut t = read_json(&src);
            for frame in t["frames"].as_array_mut().unwrap() {
                for row in frame["transform_matrix"]
                    .as_array_mut()
                    .unwrap()
                    .iter_mut()
                    .take(3)
                {
                    let x = row[3].as_f64().unwrap();
                    row[3] = serde_json::json!(x * scale);
                }
            }
            std::fs::write(dst, t.to_string()).unwrap();
        } else {
            std::fs::copy(src, dst).unwrap();
        }
    }
    let scaled =
        crate::capture::map_obj(&p.read("out/tiny/scene/skin.obj"), |v| v.map(|x| x * scale));
    p.write(&format!("{dir}/labels.obj"), &scaled);
    let gt = read_json(&scene.join("scene.json"));
    p.write(
        &format!("{dir}/scene.json"),
        &capture_scene(&gt, scale, None),
    );
    p.write(
        &format!("{dir}/capture.toml"),
        &std::fs::read_to_string(repo("pipelines/capture.toml")).unwrap(),
    );
}

/// A capture's `scene.json` from a synthetic scene's: the eyes (times `scale`), the eye
/// separation and each part's fur flag, with `s_cm` only where given (a user's file has
/// none; an `evaluate` stage's `gt_scene` needs it).
pub(crate) fn capture_scene(gt: &Json, scale: f64, s_cm: Option<f64>) -> String {
    let parts: serde_json::Map<String, Json> = gt["parts"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), serde_json::json!({ "fur": v["fur"] })))
        .collect();
    let eyes: Vec<Vec<f64>> = gt["eyes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            e.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() * scale)
                .collect()
        })
        .collect();
    let mut scene = serde_json::json!({
        "eyes": eyes,
        "eye_separation_cm": gt["eye_separation_cm"],
        "parts": parts,
    });
    if let Some(s_cm) = s_cm {
        scene["s_cm"] = s_cm.into();
    }
    scene.to_string()
}

/// The tiny capture's settings for `capture.toml`.
pub(crate) const TINY_CAPTURE: [&str; 8] = [
    "--set",
    "frosting.gaussians=1500",
    "--set",
    "frosting.iterations=40",
    "--set",
    "roots.roots_per_pixel=1.0",
    "--set",
    "codec.iterations=10",
];

/// Vertex positions of an OBJ.
fn obj_vertices(text: &str) -> Vec<[f64; 3]> {
    text.lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|r| {
            let v: Vec<f64> = r.split_whitespace().map(|x| x.parse().unwrap()).collect();
            [v[0], v[1], v[2]]
        })
        .collect()
}

/// The same capture in metres and in centimetres (every length x 100)
/// gives the same reconstruction up to the scale: the metric scale, the
/// per-part strand lengths in cm (against a reseed), the defurred surface
/// (x 100), the strands (against a reseed) and the root count.
#[test]
fn a_capture_in_centimetres_gives_the_metre_result_times_100() {
    let p = Project::new();
    p.write("tiny.toml", &tiny_pipeline());
    p.run("tiny.toml", &["--until", "scene"]).ok();
    write_capture(&p, "cap_m", 1.0);
    write_capture(&p, "cap_cm", 100.0);
    let mut args_m = TINY_CAPTURE.to_vec();
    args_m.extend(["--until", "codec", "--out", "out_m"]);
    let mut args_cm = TINY_CAPTURE.to_vec();
    args_cm.extend(["--until", "codec", "--out", "out_cm"]);
    // The yardstick for the strands: the metre capture with the codec reseeded.
    let mut args_reseed = TINY_CAPTURE.to_vec();
    args_reseed.extend([
        "--until",
        "codec",
        "--out",
        "out_m1",
        "--set",
        "codec.seed=1",
    ]);
    p.run("cap_m/capture.toml", &args_m).ok();
    p.run("cap_cm/capture.toml", &args_cm).ok();
    p.run("cap_m/capture.toml", &args_reseed).ok();
    let (m, cm) = (p.path("out_m/capture"), p.path("out_cm/capture"));

    let lm = read_json(&m.join("lengths/metrics.json"));
    let lc = read_json(&cm.join("lengths/metrics.json"));
    let (sm, sc) = (
        number(&lm, "s_cm", "lengths/metrics.json"),
        number(&lc, "s_cm", "lengths/metrics.json"),
    );
    assert!(
        (sm - 100.0 * sc).abs() < 1e-4 * sm,
        "s_cm {sm} (m) against {sc} (cm)"
    );
    let (len_m, len_cm) = (
        read_json(&m.join("lengths/lengths.json")),
        read_json(&cm.join("lengths/lengths.json")),
    );
    // The per-part lengths follow the Frosting widths, which follow the fit (the same in both
    // units up to float rounding, whose last digits move a vertex's crossing a little): the
    // yardstick is the metre capture with Frosting reseeded, which the change of units must
    // move less than a tenth as far, summed over the parts.
    let mut args_refit = TINY_CAPTURE.to_vec();
    args_refit.extend([
        "--until",
        "lengths",
        "--out",
        "out_mf",
        "--set",
        "frosting.seed=1",
    ]);
    p.run("cap_m/capture.toml", &args_refit).ok();
    let len_refit = read_json(&p.path("out_mf/capture/lengths/lengths.json"));
    let parts_m = len_m["parts"].as_object().expect("lengths.json parts");
    let (mut units, mut refit) = (0.0f64, 0.0f64);
    for (name, part) in parts_m {
        let a = part["length_cm"].as_f64().unwrap();
        let b = len_cm["parts"][name]["length_cm"].as_f64().unwrap();
        let c = len_refit["parts"][name]["length_cm"].as_f64().unwrap();
        assert!(
            (a - b).abs() <= 0.05 * a.max(0.01),
            "{name}: {a} cm (m) against {b} cm (cm)"
        );
        units += (a - b).abs();
        refit += (a - c).abs();
    }
    eprintln!("part lengths m vs cm: {units:.3} cm in all (Frosting reseeded: {refit:.3} cm)");
    assert!(
        units < 0.1 * refit,
        "part lengths differ by {units} cm in all between the units, {refit} cm for a reseed"
    );

    let vm = obj_vertices(&std::fs::read_to_string(m.join("defur/root_mesh.obj")).unwrap());
    let vc = obj_vertices(&std::fs::read_to_string(cm.join("defur/root_mesh.obj")).unwrap());
    assert_eq!(vm.len(), vc.len());
    let (lo, hi) = vm
        .iter()
        .fold(([f64::MAX; 3], [f64::MIN; 3]), |(lo, hi), v| {
            (
                [lo[0].min(v[0]), lo[1].min(v[1]), lo[2].min(v[2])],
                [hi[0].max(v[0]), hi[1].max(v[1]), hi[2].max(v[2])],
            )
        });
    let diag = ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt();
    let mut worst = 0.0f64;
    let mut sum = 0.0f64;
    for (a, b) in vm.iter().zip(&vc) {
        let d = ((a[0] - b[0] / 100.0).powi(2)
            + (a[1] - b[1] / 100.0).powi(2)
            + (a[2] - b[2] / 100.0).powi(2))
        .sqrt();
        worst = worst.max(d);
        sum += d;
    }
    let mean = sum / vm.len() as f64;
    eprintln!(
        "M_root m vs cm/100: mean {:.2e} D, max {:.2e} D",
        mean / diag,
        worst / diag
    );
    assert!(
        mean < 1e-4 * diag && worst < 1e-3 * diag,
        "mean {mean}, max {worst}, D {diag}"
    );
    // The learnt strands, matched by their roots: every strand's points x
    // 100 against those of the strand rooted nearest. The metric scale from
    // the eyes differs in its last digits between the units, so a triangle
    // whose expected root count sits at a rounding edge may round it the
    // other way (`placement = "local"` keeps that to the triangle; the
    // systematic sampling's running sum carried it to every later triangle:
    // 77 of 3413 roots seen) and every later index shifts.
    let read = |dir: &std::path::Path| {
        fure_stages::formats::hair::read_hair(dir.join("codec/strands.hair")).unwrap()
    };
    let (hm, hc, hr) = (read(&m), read(&cm), read(&p.path("out_m1/capture")));
    let strand = |h: &fure_stages::data::strands::Strands, i: usize| -> Vec<[f64; 3]> {
        h.points[h.starts[i] as usize..h.starts[i + 1] as usize]
            .iter()
            .map(|p| p.to_array().map(f64::from))
            .collect()
    };
    let dist = |a: [f64; 3], b: [f64; 3], div: f64| -> f64 {
        ((a[0] - b[0] / div).powi(2) + (a[1] - b[1] / div).powi(2) + (a[2] - b[2] / div).powi(2))
            .sqrt()
    };
    let nm = hm.starts.len() - 1;
    // Strands of `h` (lengths / div) twinned by root with the metre run's:
    // how many have no twin, and the mean point distance of the twins.
    let compare = |h: &fure_stages::data::strands::Strands, div: f64| -> (usize, f64) {
        let n = h.starts.len() - 1;
        assert!(
            nm.abs_diff(n) as f64 <= 0.005 * nm as f64,
            "strands {nm} (m) against {n}"
        );
        let roots: Vec<[f64; 3]> = (0..n).map(|i| strand(h, i)[0]).collect();
        let (mut sum, mut count, mut unmatched) = (0.0f64, 0usize, 0usize);
        for i in 0..nm {
            let a = strand(&hm, i);
            let (j, d) = roots
                .iter()
                .enumerate()
                .map(|(j, r)| (j, dist(a[0], *r, div)))
                .fold((0, f64::MAX), |b, c| if c.1 < b.1 { c } else { b });
            let b = strand(h, j);
            if d > 1e-3 * diag || a.len() != b.len() {
                unmatched += 1;
                continue;
            }
            for (p, q) in a.iter().zip(&b) {
                sum += dist(*p, *q, div);
                count += 1;
            }
        }
        (unmatched, sum / count.max(1) as f64)
    };
    let (unmatched, dev) = compare(&hc, 100.0);
    let (_, reseed) = compare(&hr, 1.0);
    eprintln!(
        "strands m vs cm/100: {unmatched} of {nm} without a twin, mean point deviation {:.2e} D \
         (the codec reseeded: {:.2e} D)",
        dev / diag,
        reseed / diag
    );
    assert!(
        unmatched as f64 <= 0.05 * nm as f64,
        "{unmatched} of {nm} strands have no twin"
    );
    // The strands are trained on seeded strand subsets drawn from slightly
    // different root sets, so they agree up to training noise: the change
    // of units must move them less than half as far as a new codec seed.
    assert!(
        dev < 0.5 * reseed && dev < 1e-3 * diag,
        "strand points differ by {dev} on average (a reseed: {reseed}), D {diag}"
    );

    let rm = read_json(&m.join("roots/metrics.json"));
    let rc = read_json(&cm.join("roots/metrics.json"));
    let (nm, nc) = (
        number(&rm, "total", "roots/metrics.json"),
        number(&rc, "total", "roots/metrics.json"),
    );
    assert!(
        (nm - nc).abs() <= 0.005 * nm,
        "roots {nm} (m) against {nc} (cm)"
    );
}

/// `speed_accuracy.toml` (which extends `tiger_ablations.toml`) after
/// `tiger.toml` on one cache: everything up to the defurring, the roots and
/// the full method's learner comes from the cache, only the ablations, the
/// dense baseline, their evaluations and the chart stage run, and the chart
/// stage writes its charts, tables and the speed-up (a number, or null with
/// a note saying why).
#[test]
fn speed_accuracy_reuses_the_tiger_run_and_charts_both_learners() {
    let p = Project::new();
    p.write("tiny.toml", &tiny_pipeline());
    let learners = "
[stages.codec_fixed]
iterations = 10

[stages.codec_prior]
iterations = 10

[stages.dense]
iterations = 30
";
    p.write(
        "tiny_sa.toml",
        &(tiny_extension("pipelines/speed_accuracy.toml", "tiny_sa") + learners),
    );
    p.run("tiny.toml", &[]).ok();
    let r = p.run("tiny_sa.toml", &[]);
    r.ok();
    assert_eq!(r.with("cached"), TIGER_STAGES, "{:?}", r.stages);
    assert_eq!(
        r.with("ran"),
        [
            "codec_fixed",
            "codec_prior",
            "dense",
            "evaluate_dense",
            "evaluate_fixed",
            "evaluate_prior",
            "speed_accuracy"
        ],
        "{:?}",
        r.stages
    );

    let out = p.path("out/tiny_sa/speed_accuracy");
    for f in [
        "chart_time.png",
        "chart_time_svg.svg",
        "chart_params.png",
        "chart_params_svg.svg",
        "table_md.md",
        "table_csv.csv",
    ] {
        let len = std::fs::metadata(out.join(f))
            .unwrap_or_else(|e| panic!("{f}: {e}"))
            .len();
        assert!(len > 0, "{f} is empty");
    }
    let m = read_json(&out.join("metrics.json"));
    let speedup = &m["speedup_to_dense_final_fscore"];
    match speedup.as_f64() {
        Some(x) => assert!(x.is_finite() && x >= 0.0, "speed-up {x}"),
        None => {
            assert!(speedup.is_null(), "speed-up {speedup}");
            let note = m["speedup_note"].as_str().unwrap_or_default();
            assert!(
                note.contains("never reached") || note.contains("undefined"),
                "{note}"
            );
        }
    }
    for key in [
        "dense_final_fscore_3cm_30deg",
        "codec_final_fscore_3cm_30deg",
    ] {
        let f = number(&m, key, "speed_accuracy/metrics.json");
        assert!((0.0..=100.0).contains(&f), "{key} = {f}");
    }
    let methods: BTreeSet<&str> = m["snapshots"]
        .as_array()
        .expect("snapshots")
        .iter()
        .map(|s| s["method"].as_str().unwrap_or_default())
        .collect();
    assert_eq!(methods, BTreeSet::from(["codec", "dense"]));
}

/// The scene's output files a `scene.PORT` input stands for.
fn scene_file(port: &str) -> &'static str {
    match port {
        "views" => "views",
        "labels" => "labels.obj",
        "scene" => "scene.json",
        "skin" => "skin.obj",
        "strands" => "strands.hair",
        "regrown" => "regrown.hair",
        other => panic!("tiger.toml reads scene.{other}: add it to the ground-truth boundary test"),
    }
}

/// `tiger.toml` with every `scene.*` input replaced by the same file under `dir`.
fn from_files(dir: &str, name: &str) -> String {
    let doc: toml::Table = std::fs::read_to_string(repo("pipelines/tiger.toml"))
        .unwrap()
        .parse()
        .unwrap();
    let mut s = format!("extends = 'tiny.toml'\n\n[pipeline]\nname = \"{name}\"\n");
    for (stage, t) in doc["stages"].as_table().unwrap() {
        let Some(inputs) = t.get("inputs").and_then(|i| i.as_table()) else {
            continue;
        };
        let mut over = Vec::new();
        for (port, v) in inputs {
            if let Some(out) = v.as_str().and_then(|v| v.strip_prefix("scene.")) {
                over.push(format!("{port} = \"{dir}/{}\"", scene_file(out)));
            }
        }
        if !over.is_empty() {
            s.push_str(&format!(
                "\n[stages.{stage}]\ninputs = {{ {} }}\n",
                over.join(", ")
            ));
        }
    }
    s
}

/// The ground-truth boundary: only ports named `gt_*` read ground truth. The same capture is
/// given twice, once with its ground truth intact and once scrambled (every per-part statistic
/// and fur flag of scene.json, s_cm, the GT skin moved, the GT strands replaced by another
/// animal): every reconstruction output is byte-identical, stages without a `gt_*` input are
/// cache hits (their keys never saw the difference), and the metrics do change.
#[test]
fn ground_truth_reaches_only_gt_ports() {
    let p = Project::new();
    p.write("tiny.toml", &tiny_pipeline());
    p.run("tiny.toml", &["--until", "scene"]).ok();
    let scene = p.path("out/tiny/scene");
    for dir in ["a", "b"] {
        for f in files(&scene) {
            let dst = p.path(dir).join(&f);
            std::fs::create_dir_all(dst.parent().unwrap()).unwrap();
            std::fs::copy(scene.join(&f), dst).unwrap();
        }
    }
    // Scramble b's ground truth.
    let mut gt = read_json(&scene.join("scene.json"));
    gt["s_cm"] = Json::from(gt["s_cm"].as_f64().unwrap() * 3.0);
    for (_, part) in gt["parts"].as_object_mut().unwrap() {
        let part = part.as_object_mut().unwrap();
        let fur = part["fur"].as_bool().unwrap();
        part.insert("fur".into(), Json::from(!fur));
        for k in ["mean_length_cm", "density_per_cm2", "mean_thickness_cm"] {
            let x = part.get(k).and_then(|x| x.as_f64()).unwrap_or(1.0);
            part.insert(k.into(), Json::from(x * 7.0 + 1.0));
        }
    }
    p.write("b/scene.json", &gt.to_string());
    let skin: String = p
        .read("b/skin.obj")
        .lines()
        .map(|l| match l.strip_prefix("v ") {
            Some(xyz) => {
                let v: Vec<f64> = xyz.split_whitespace().map(|x| x.parse().unwrap()).collect();
                format!("v {} {} {}\n", v[0] * 0.9, v[1] * 0.9 + 0.01, v[2] * 0.9)
            }
            None => format!("{l}\n"),
        })
        .collect();
    p.write("b/skin.obj", &skin);
    std::fs::copy(scene.join("regrown.hair"), p.path("b/strands.hair")).unwrap();

    p.write("a.toml", &from_files("a", "gta"));
    p.write("b.toml", &from_files("b", "gtb"));
    p.run("a.toml", &[]).ok();
    let r = p.run("b.toml", &[]);
    r.ok();

    let reconstruction = [
        "outer",
        "parts",
        "frosting",
        "lengths",
        "defur_baseline",
        "defur",
        "roots",
        "basis",
        "orientation",
        "codec",
        "groom",
    ];
    for stage in reconstruction {
        let (da, db) = (p.path("out/gta").join(stage), p.path("out/gtb").join(stage));
        let fa = files(&da);
        assert!(!fa.is_empty(), "{stage}: no outputs");
        assert_eq!(fa, files(&db), "{stage}: output files differ");
        for f in fa.iter().filter(|f| !f.ends_with("metrics.json")) {
            assert!(
                std::fs::read(da.join(f)).unwrap() == std::fs::read(db.join(f)).unwrap(),
                "{stage}/{}: the scrambled ground truth changed a reconstruction output",
                f.display()
            );
        }
    }
    // Stages without a gt_* input kept their keys: cache hits.
    for stage in [
        "outer",
        "parts",
        "roots",
        "basis",
        "orientation",
        "codec",
        "groom",
    ] {
        assert_eq!(r.status(stage), "cached", "{stage}: {}", r.reason(stage));
    }
    // The scrambling reached the metrics (so the test compares what it claims to).
    let m = |run: &str| read_json(&p.path(&format!("out/{run}/evaluate/metrics.json")));
    assert_ne!(
        m("gta")["prf"],
        m("gtb")["prf"],
        "the GT strands were not swapped"
    );
    let d = |run: &str| read_json(&p.path(&format!("out/{run}/defur/metrics.json")));
    assert_ne!(
        d("gta")["root_to_skin_mean_cm"],
        d("gtb")["root_to_skin_mean_cm"],
        "the GT skin was not moved"
    );
}

/// `benchmark.toml` on the suite's smallest scene (the cat) at the tiny sizes, two seeds, as CI
/// can afford it: every run ends ok, the report aggregates both seeds, and the results document,
/// its charts and the per-run CSV are published with the provenance stamp where the child
/// pipeline says (the shipped destinations are replaced, so the repo's docs/ is untouched).
#[test]
fn benchmark_suite_runs_on_its_smallest_scene_and_publishes_the_results() {
    let p = Project::new();
    let extra = r#"
[stages.codec_fixed]
iterations = 10

[stages.codec_prior]
iterations = 10

[stages.codec_human]
iterations = 10

[stages.codec_v2]
iterations = 10

[stages.dense]
iterations = 30

[sweep]
"scene.preset,defur_baseline.species,lengths_v2.species" = ["cat"]
"scene.seed,frosting.seed,roots.seed,roots_v2.seed,codec.seed,codec_fixed.seed,codec_prior.seed,codec_human.seed,codec_v2.seed,dense.seed" = [0, 1]

[publish]
"report.results" = "docs/results.md"
"report.charts" = "docs/benchmark"
"report.runs" = "docs/benchmark/runs.csv"
"report.headline" = "README.md#benchmark-headline"
"#;
    p.write(
        "bench.toml",
        &(tiny_extension("pipelines/benchmark.toml", "bench") + extra),
    );
    let readme = "# Demo\n<!-- fure:begin benchmark-headline -->\nstale\n<!-- fure:end benchmark-headline -->\nprose\n";
    p.write("README.md", readme);
    let out = p.fure(&["sweep", "bench.toml"]);
    let text = format!(
        "stdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{text}");
    assert!(text.contains("0 of 2 variants failed"), "{text}");

    let md = p.read("docs/results.md");
    assert!(md.contains("## Headline, test split"), "{md}");
    // The targets table reads the codec against its goals on the test scene, before the scenes.
    let targets = md.find("## Targets, test split: FurE codec").expect(&md);
    assert!(targets < md.find("## Per scene").unwrap(), "{md}");
    assert!(md[targets..].contains("\n| cat | "), "{md}");
    // The README's section now holds the stamped headline table; its prose is untouched.
    let readme = p.read("README.md");
    assert!(
        readme.starts_with("# Demo\n<!-- fure:begin benchmark-headline -->\nGenerated "),
        "{readme}"
    );
    assert!(
        readme.contains("### Headline, test split") && readme.contains("| cat (1 cm) | 2 |"),
        "{readme}"
    );
    assert!(
        readme.ends_with("<!-- fure:end benchmark-headline -->\nprose\n")
            && !readme.contains("stale"),
        "{readme}"
    );
    assert!(md.contains("Generated "), "no provenance stamp: {md}");
    assert!(!md.contains("fure:provenance"), "{md}");
    for method in [
        "FurE codec",
        "dense",
        "fixed length",
        "shape prior",
        "human basis",
        "V2 lengths",
        "ceiling",
    ] {
        assert!(
            md.contains(&format!("| {method} |")),
            "no row for {method}: {md}"
        );
    }
    let m = read_json(&p.path("out/bench/report/metrics.json"));
    let cat = &m["scenes"]["cat"];
    assert_eq!(cat["split"], "test", "{m}");
    for method in ["FurE codec", "dense", "ceiling"] {
        let f = &cat[method]["signed_f_3cm_30deg"];
        assert_eq!(f["n"], 2, "{method}: {f}");
        let mean = f["mean"].as_f64().unwrap();
        assert!((0.0..=100.0).contains(&mean), "{method}: {f}");
    }
    // The regrown animal is close to the truth: its score is a ceiling, above the tiny learners.
    let ceiling = cat["ceiling"]["signed_f_3cm_30deg"]["mean"]
        .as_f64()
        .unwrap();
    let codec = cat["FurE codec"]["signed_f_3cm_30deg"]["mean"]
        .as_f64()
        .unwrap();
    assert!(ceiling > codec, "ceiling {ceiling} <= codec {codec}");
    assert!(
        cat["preprocessing"]["seconds"]["mean"].as_f64().unwrap() > 0.0,
        "{m}"
    );
    for f in ["f_vs_time_cat.svg", "f_vs_size_cat.png", "runs.csv"] {
        assert!(
            p.path("docs/benchmark").join(f).is_file(),
            "{f} not published"
        );
    }
    assert_eq!(p.read("docs/benchmark/runs.csv").lines().count(), 1 + 2 * 7);
    // V2 (species reference lengths) is reported beside V1, from its own lengths stage.
    assert!(
        cat["preprocessing"]["length_error_v2_mean_pct"]["n"] == 2,
        "{m}"
    );
}

/// `--device` sets the parameter on every stage that renders; the device
/// that ran is recorded in the learner's metrics.json; a device that does not
/// exist is refused before anything runs.
#[test]
fn the_device_flag_reaches_the_renderers_and_is_recorded() {
    let p = Project::new();
    p.write("tiny.toml", &tiny_pipeline());
    let bad = p.run("tiny.toml", &["--until", "codec", "--device", "tpu"]);
    assert_ne!(bad.code(), 0, "{}", bad.stdout());
    let msg = format!("{}{}", bad.stdout(), bad.stderr());
    assert!(msg.contains("tpu") && msg.contains("device"), "{msg}");
    assert!(bad.with("ran").is_empty(), "{:?}", bad.stages);

    let r = p.run("tiny.toml", &["--until", "codec", "--device", "cpu"]);
    r.ok();
    let codec = read_json(&p.path("out/tiny/codec/metrics.json"));
    assert_eq!(codec["device"]["device"], "cpu", "{codec}");
    // ... and in the run report, as the stage's note, also for a cache hit.
    let notes = |r: &crate::engine::Run, stage: &str| -> Vec<String> {
        r.json["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == stage)
            .map(|s| serde_json::from_value(s["notes"].clone()).unwrap_or_default())
            .unwrap_or_default()
    };
    for stage in ["frosting", "codec"] {
        let n = notes(&r, stage);
        assert!(n.iter().any(|l| l == "renders on cpu"), "{stage}: {n:?}");
    }
    // The same run with the parameter given per stage hits the cache: the
    // flag is only a shorthand for the parameter.
    let again = p.run(
        "tiny.toml",
        &[
            "--until",
            "codec",
            "--set",
            "codec.device=cpu",
            "--set",
            "frosting.device=cpu",
            "--set",
            "orientation.device=cpu",
        ],
    );
    again.ok();
    assert_eq!(again.status("codec"), "cached", "{:?}", again.stages);
    assert!(notes(&again, "codec").iter().any(|l| l == "renders on cpu"));

    // The learner on the GPU (image losses fused on the device), from the
    // same upstream stages: its first iteration scores what the CPU's does,
    // and training ends near it.
    let g = p.run(
        "tiny.toml",
        &["--until", "codec", "--set", "codec.device=gpu"],
    );
    if g.code() != 0 {
        let msg = format!("{}{}", g.stdout(), g.stderr());
        assert!(msg.contains("adapter") || msg.contains("feature"), "{msg}");
        eprintln!("SKIPPED: the GPU learner needs the gpu feature and an adapter: {msg}");
        return;
    }
    let gcodec = read_json(&p.path("out/tiny/codec/metrics.json"));
    assert_eq!(gcodec["device"]["device"], "gpu", "{gcodec}");
    let first = |m: &serde_json::Value| m["loss_history"][0].as_f64().unwrap();
    let (c0, g0) = (first(&codec), first(&gcodec));
    assert!(
        (c0 - g0).abs() <= 1e-4 * c0.abs().max(1e-3),
        "first loss cpu {c0} gpu {g0}"
    );
    let total = |m: &serde_json::Value| m["final_losses"]["total"].as_f64().unwrap();
    let (ct, gt) = (total(&codec), total(&gcodec));
    assert!((ct - gt).abs() <= 0.05 * ct, "final loss cpu {ct} gpu {gt}");
}

/// Issue 14's controlled test of the thickness cue: the same tiger twice, the second time
/// with its torso's fur standing up (several times thicker, several pixels at 160 px) and
/// nothing else changed. With `inner_level` (the fit's translucent fringe) the torso's width
/// grows by more than 1.4 times as much as the widths of parts away from the torso. The
/// pipelines' `inner_depth` reading hardly moves here (docs/history.md, "Frosting: a reading that
/// follows the fur").
#[test]
fn frosting_widths_follow_a_thicker_fur_on_one_part() {
    let p = Project::new();
    let pipeline = |name: &str| {
        format!(
            r#"extends = '{}'

[pipeline]
name = "{name}"

[stages.scene]
resolution = 160
views = 24
test_views = 1

[stages.frosting]
width_reading = "frosting"
inner_level = 0.5
range_sigmas = 6.0
samples = 61
"#,
            repo("pipelines/tiger.toml").display()
        )
    };
    p.write("flat.toml", &pipeline("flat"));
    p.write(
        "raised.toml",
        &format!(
            "{}\n[stages.scene.parts.torso]\nlift_deg = 80.0\nlength_cm = 6.0\n",
            pipeline("raised")
        ),
    );
    let (mut width, mut truth) = (Vec::new(), Vec::new());
    for name in ["flat", "raised"] {
        p.run(&format!("{name}.toml"), &["--until", "frosting"])
            .ok();
        let m = read_json(&p.path(&format!("out/{name}/frosting/metrics.json")));
        let scene = read_json(&p.path(&format!("out/{name}/scene/scene.json")));
        width.push(m["part_median_width"].clone());
        truth.push(number(
            &scene["parts"]["torso"],
            "mean_thickness_cm",
            "scene.json",
        ));
    }
    let ratio = |part: &str| {
        number(&width[1], part, "raised metrics.json")
            / number(&width[0], part, "flat metrics.json")
    };
    assert!(truth[1] > 3.0 * truth[0], "GT torso thickness {truth:?}");
    // The longer fur also moves the framing and M_outer's area (hence the Gaussians' spacing),
    // so every part's width moves a little, together; the torso's must move well beyond them.
    let controls: Vec<f64> = ["head", "front_legs", "hind_legs", "tail"]
        .iter()
        .map(|part| ratio(part))
        .collect();
    let (lo, hi) = controls
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), &r| {
            (lo.min(r), hi.max(r))
        });
    assert!(hi / lo < 1.2, "untouched parts' ratios {controls:?}");
    assert!(
        ratio("torso") > 1.4 * hi,
        "torso ratio {} against untouched parts' {controls:?}, widths {width:?}",
        ratio("torso")
    );
}

/// Issue 15's direction test on a dev scene, at the shipped size (`pipelines/tiger.toml`, seed 0):
/// every root frame turned 45 degrees about its normal, the codec's start frames turned onto the
/// fur's axis the views show and its learned angle bring the mean in-plane direction error
/// within 15 degrees of the GT's growth direction (13.6 measured); without both, the same start
/// stays beyond 30 (42.4 measured), so it is the method that turns the strands back.
#[test]
fn a_start_turned_45_degrees_is_brought_back_within_15_degrees_on_the_tiger() {
    let p = Project::new();
    p.write(
        "turned.toml",
        &tiger_as("turned", "[stages.codec]\nframe_rotation_deg = 45.0\n"),
    );
    let error = |extra: &[&str]| -> f64 {
        let mut args = vec!["--until", "evaluate"];
        args.extend_from_slice(extra);
        p.run("turned.toml", &args).ok();
        let eval = read_json(&p.path("out/turned/evaluate/metrics.json"));
        number(&eval, "direction_error_deg", "evaluate/metrics.json")
    };
    let method = error(&[]);
    let unaided = error(&[
        "--set",
        "codec.view_axes_radius_px=0.0",
        "--set",
        "codec.learn_rotation=false",
    ]);
    assert!(method <= 15.0, "from a 45-degree turn: {method} degrees");
    assert!(
        unaided > 30.0,
        "without the views' axes and the learned angle: {unaided} degrees"
    );
}

/// Issue 15's seam test on a dev scene, at the shipped size (`pipelines/tiger.toml`, seed 0): at
/// no part boundary do the codec's strands turn more than the GT's do there, by more than 5
/// degrees (`evaluate`'s `seams`, evaluation::seams; 1.1 measured, at hind_legs|torso, where
/// the issue once saw the direction flip). The measure's own tests show it finds a flipped part.
#[test]
fn the_tiger_has_no_direction_seam_the_gt_does_not_have() {
    let p = Project::new();
    p.write("seams.toml", &tiger_as("seams", ""));
    p.run("seams.toml", &["--until", "evaluate"]).ok();
    let eval = read_json(&p.path("out/seams/evaluate/metrics.json"));
    let excess = &eval["seams"]["excess"];
    let judged = number(excess, "boundaries_judged", "evaluate/metrics.json");
    let worst = number(excess, "worst_excess_deg", "evaluate/metrics.json");
    assert!(judged >= 5.0, "only {judged} boundaries judged: {excess}");
    assert!(worst <= 5.0, "a seam: {excess}");
}

/// Issue 14's budget test of the thickness cue, at the benchmark's size (the tiger at 256 px,
/// 36 views, the pipelines' reading): doubling the Gaussians moves the mean width, over seeds
/// 0-2, by less than the seed spread. The composited-opacity profile reads the depth where the
/// fit turns opaque, which the images fix, rather than a level of the summed density, which
/// grows with the number of overlapping Gaussians (+16 % here). Measured to hold at this size
/// and window only (docs/history.md, "Frosting: the depth where the fit turns opaque, whatever
/// the budget": at 160 px, or with a wider window, the reading still moves a few per cent).
#[test]
fn frosting_widths_do_not_follow_the_gaussian_budget() {
    let p = Project::new();
    p.write("budget.toml", &tiger_as("budget", ""));
    let mean_width = |seed: u32, gaussians: u32| -> f64 {
        let sets = [
            format!("scene.seed={seed}"),
            format!("frosting.seed={seed}"),
            format!("frosting.gaussians={gaussians}"),
        ];
        let mut args = vec!["--until", "frosting"];
        for s in &sets {
            args.extend(["--set", s.as_str()]);
        }
        p.run("budget.toml", &args).ok();
        let m = read_json(&p.path("out/budget/frosting/metrics.json"));
        let w = &m["widths"];
        assert!(
            number(w, "at_min_fraction", "metrics.json") < 0.1,
            "widths at their floor: {w}"
        );
        number(w, "mean", "metrics.json")
    };
    let stats = |v: &[f64]| {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (v.len() - 1) as f64;
        (mean, var.sqrt())
    };
    let base: Vec<f64> = (0..3).map(|s| mean_width(s, 12_000)).collect();
    let doubled: Vec<f64> = (0..3).map(|s| mean_width(s, 24_000)).collect();
    let ((m1, s1), (m2, s2)) = (stats(&base), stats(&doubled));
    assert!(
        (m2 - m1).abs() < s1.max(s2),
        "mean width {m1} (sd {s1}) at 12,000 Gaussians, {m2} (sd {s2}) at 24,000"
    );
}
