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
default_density = 0.1

[stages.codec]
iterations = 10
"#,
        repo(pipeline).display()
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
    assert_eq!(r.with("ran"), ["codec", "evaluate", "groom"], "{:?}", r.stages);
    assert_eq!(r.with("cached").len(), TIGER_STAGES.len() - 3);
}

#[test]
fn capture_pipeline_runs_on_a_capture_without_ground_truth() {
    let p = Project::new();
    p.write("tiny.toml", &tiny_pipeline());
    p.run("tiny.toml", &["--until", "scene"]).ok();

    // A "user's capture": the views, the eyes and a labelled mesh, nothing else.
    let scene = p.path("out/tiny/scene");
    for f in files(&scene.join("views")) {
        let bytes = std::fs::read(scene.join("views").join(&f)).unwrap();
        let dst = p.path("cap/views").join(&f);
        std::fs::create_dir_all(dst.parent().unwrap()).unwrap();
        std::fs::write(dst, bytes).unwrap();
    }
    p.write("cap/labels.obj", &p.read("out/tiny/scene/skin.obj"));
    let gt = read_json(&scene.join("scene.json"));
    let parts: serde_json::Map<String, Json> = gt["parts"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), serde_json::json!({ "fur": v["fur"] })))
        .collect();
    let capture = serde_json::json!({
        "s_cm": 1.0,
        "eyes": gt["eyes"],
        "eye_separation_cm": gt["eye_separation_cm"],
        "parts": parts,
    });
    p.write("cap/scene.json", &capture.to_string());
    p.write(
        "cap/capture.toml",
        &std::fs::read_to_string(repo("pipelines/capture.toml")).unwrap(),
    );

    let r = p.run(
        "cap/capture.toml",
        &[
            "--set",
            "frosting.gaussians=1500",
            "--set",
            "frosting.iterations=40",
            "--set",
            "roots.default_density=0.1",
            "--set",
            "codec.iterations=10",
        ],
    );
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

[stages.dense]
iterations = 30

[sweep]
"scene.preset,defur_baseline.species" = ["cat"]
"scene.seed,frosting.seed,roots.seed,codec.seed,codec_fixed.seed,codec_prior.seed,dense.seed" = [0, 1]

[publish]
"report.results" = "docs/results.md"
"report.charts" = "docs/benchmark"
"report.runs" = "docs/benchmark/runs.csv"
"#;
    p.write(
        "bench.toml",
        &(tiny_extension("pipelines/benchmark.toml", "bench") + extra),
    );
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
    assert!(md.contains("Generated "), "no provenance stamp: {md}");
    assert!(!md.contains("fure:provenance"), "{md}");
    for method in [
        "FurE codec",
        "dense",
        "fixed length",
        "shape prior",
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
    assert_eq!(p.read("docs/benchmark/runs.csv").lines().count(), 1 + 2 * 5);
}
