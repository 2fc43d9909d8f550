//! Bad input through the `fure` binary: every case fails with a non-zero exit
//! code and a message naming the file (or TOML location), the position or
//! field and what was expected; prints no panic or backtrace; leaves no cache
//! entry and no staging directory for the failing stage; and once the input is
//! fixed the same command succeeds.
//!
//! The scene is the synthetic tiger at its quickest (6 views of 48 px, made in
//! about 0.1 s), generated once per test into a temporary directory and copied
//! to plain writable files under `data/`, which the tests then corrupt. The
//! pipelines read those copies as file inputs, like a user's capture.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value as Json;

/// A project directory with a generated scene under `data/`.
struct Scene {
    dir: tempfile::TempDir,
}

/// The quick scene: small, fast, and enough views for a visual hull.
const GEN: &str = r#"
[stages.scene]
kind = "synthetic_scene"
size = "quick"
views = 6
test_views = 1
resolution = 48
supersample = 1
"#;

/// Visual hull from the views, then parts from the GT skin.
const HULL: &str = r#"
[stages.outer]
kind = "outer_surface"
inputs = { views = "data/views" }

[stages.parts]
kind = "parts"
inputs = { mesh = "outer.mesh", labels = "data/skin.obj" }
"#;

/// A user's mesh imported by outer_surface, then labelled.
const IMPORT: &str = r#"
[stages.outer]
kind = "outer_surface"
inputs = { mesh = "data/outer.obj" }

[stages.parts]
kind = "parts"
inputs = { mesh = "outer.mesh", labels = "data/skin.obj" }
"#;

/// A user's mesh labelled directly.
const PARTS: &str = r#"
[stages.parts]
kind = "parts"
inputs = { mesh = "data/outer.obj", labels = "data/skin.obj" }
"#;

impl Scene {
    fn new() -> Scene {
        let s = Scene {
            dir: tempfile::tempdir().expect("temp dir"),
        };
        s.write("gen.toml", GEN.as_bytes());
        let out = s.fure(&[
            "run", "gen.toml", "--plain", "--cache", "gencache", "--out", "gen",
        ]);
        assert!(
            out.status.success(),
            "scene generation failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        copy_tree(&s.path("gen/gen/scene/views"), &s.path("data/views"));
        for f in ["skin.obj", "scene.json"] {
            let bytes = std::fs::read(s.path(&format!("gen/gen/scene/{f}"))).unwrap();
            s.write(&format!("data/{f}"), &bytes);
        }
        s.write("hull.toml", HULL.as_bytes());
        s
    }
    fn path(&self, rel: &str) -> PathBuf {
        self.dir.path().join(rel)
    }
    fn write(&self, rel: &str, bytes: &[u8]) {
        let p = self.path(rel);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        let _ = std::fs::remove_file(&p);
        std::fs::write(p, bytes).unwrap();
    }
    fn read(&self, rel: &str) -> Vec<u8> {
        std::fs::read(self.path(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
    }
    fn text(&self, rel: &str) -> String {
        String::from_utf8(self.read(rel)).unwrap()
    }
    fn fure(&self, args: &[&str]) -> Output {
        Command::new(env!("CARGO_BIN_EXE_fure"))
            .args(args)
            .current_dir(self.dir.path())
            .env("FURE_CACHE", self.path("cache"))
            .env_remove("RUST_BACKTRACE")
            .output()
            .expect("run fure")
    }
    /// Cache entries whose manifest names `stage` of pipeline `pipeline`.
    fn entries(&self, pipeline: &str, stage: &str) -> usize {
        let Ok(rd) = std::fs::read_dir(self.path("cache/entries")) else {
            return 0;
        };
        rd.filter_map(|e| std::fs::read(e.ok()?.path()).ok())
            .filter_map(|b| serde_json::from_slice::<Json>(&b).ok())
            .filter(|m| m["stage"] == stage && m["pipeline"] == pipeline)
            .count()
    }
    /// Runs `pipeline` (a file in the project) and checks the failure contract;
    /// returns stderr.
    fn fails(&self, pipeline: &str, stage: &str, wants: &[&str]) -> String {
        self.fails_with(&["run", pipeline, "--plain"], pipeline, stage, wants)
    }
    fn fails_with(&self, args: &[&str], pipeline: &str, stage: &str, wants: &[&str]) -> String {
        let name = Path::new(pipeline).file_stem().unwrap().to_str().unwrap();
        let before = self.entries(name, stage);
        let out = self.fure(args);
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(
            !out.status.success(),
            "`fure {}` should fail; stderr:\n{err}",
            args.join(" ")
        );
        for w in wants {
            assert!(err.contains(w), "missing `{w}` in stderr:\n{err}");
        }
        for bad in ["panicked", "RUST_BACKTRACE", "stack backtrace", "unwrap()"] {
            assert!(!err.contains(bad), "`{bad}` in stderr:\n{err}");
        }
        assert_eq!(
            self.entries(name, stage),
            before,
            "a failing stage `{stage}` left a cache entry"
        );
        if let Ok(rd) = std::fs::read_dir(self.path("cache/tmp")) {
            let left: Vec<_> = rd.filter_map(|e| e.ok()).map(|e| e.file_name()).collect();
            assert!(left.is_empty(), "staging dirs left behind: {left:?}");
        }
        // `status` agrees: the failing stage has to run again.
        let st = self.fure(&["status", pipeline]);
        let text = String::from_utf8_lossy(&st.stdout).into_owned();
        if st.status.success() {
            let line = text
                .lines()
                .find(|l| l.split_whitespace().next() == Some(stage))
                .unwrap_or_else(|| panic!("no `{stage}` in status:\n{text}"));
            assert!(line.contains("will run"), "{line}");
        }
        err
    }
    /// Runs `pipeline` and expects success; returns stdout.
    fn succeeds(&self, pipeline: &str) -> String {
        let out = self.fure(&["run", pipeline, "--plain"]);
        assert!(
            out.status.success(),
            "`fure run {pipeline}` should succeed; stderr:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &dst);
        } else {
            // Read and write (not fs::copy): the cache's objects are read-only.
            std::fs::write(&dst, std::fs::read(e.path()).unwrap()).unwrap();
        }
    }
}

fn json(bytes: &[u8]) -> Json {
    serde_json::from_slice(bytes).unwrap()
}

fn pretty(v: &Json) -> Vec<u8> {
    serde_json::to_vec_pretty(v).unwrap()
}

// ---------------------------------------------------------------- pipelines

#[test]
fn malformed_pipelines_are_located_and_fixed_pipelines_run() {
    // engine.rs covers `x = = 3`, unknown kinds and parameters, ports and cycles;
    // these are the other ways a pipeline file can be broken.
    let s = Scene::new();
    let cases: &[(&str, &[&str])] = &[
        // Truncated mid-string.
        (
            "[stages.outer]\nkind = \"outer_surf",
            &["p.toml:2:", "invalid TOML"],
        ),
        // A stage that is not a table.
        (
            "stages.outer = 3\n",
            &["p.toml:1:", "`stages.outer` must be a table"],
        ),
        // kind of the wrong type.
        (
            "[stages.outer]\nkind = 3\n",
            &["p.toml:2:1: error", "`stages.outer.kind` must be a string"],
        ),
        // Duplicate key.
        (
            "[stages.outer]\nkind = \"outer_surface\"\nkind = \"parts\"\n",
            &["p.toml:3:", "invalid TOML"],
        ),
        // Dates are TOML but no parameter takes one.
        (
            "[stages.outer]\nkind = \"outer_surface\"\nvoxel_pixels = 1979-05-27\ninputs = { views = \"data/views\" }\n",
            &["p.toml:3:16: error: dates are not supported"],
        ),
        // A misspelt kind next to a correct stage.
        (
            "[stages.outer]\nkind = \"outer_surfaces\"\ninputs = { views = \"data/views\" }\n",
            &["p.toml:2:8: error: stage `outer`: unknown kind `outer_surfaces`", "outer_surface"],
        ),
        // An input file that does not exist.
        (
            "[stages.outer]\nkind = \"outer_surface\"\ninputs = { views = \"data/veiws\" }\n",
            &["p.toml:3:20: error: input `data/veiws` is neither an output of a stage", "data/veiws"],
        ),
    ];
    for (text, wants) in cases {
        s.write("p.toml", text.as_bytes());
        let out = s.fure(&["run", "p.toml", "--plain"]);
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert_eq!(out.status.code(), Some(2), "{text}\n{err}");
        for w in *wants {
            assert!(err.contains(w), "`{text}`: missing `{w}` in:\n{err}");
        }
        assert!(!err.contains("panicked"), "{err}");
        assert!(!s.path("out/p").exists(), "nothing may run: {text}");
    }
    // Not UTF-8 at all.
    s.write("p.toml", &[0xff, 0xfe, 0x00, 0x5b, 0x80]);
    let out = s.fure(&["run", "p.toml"]);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("p.toml"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    // A pipeline file that does not exist.
    let out = s.fure(&["run", "nope.toml"]);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("cannot read pipeline `nope.toml`"), "{err}");
    // Fixed: the same command runs.
    s.write("p.toml", HULL.as_bytes());
    s.succeeds("p.toml");
}

#[test]
fn nan_inf_zero_and_negative_parameters_are_rejected_with_their_location() {
    let s = Scene::new();
    let bad = r#"
[stages.outer]
kind = "outer_surface"
voxel_pixels = nan
mask_threshold = 0
resolution = -5
min_views_outside = inf
inputs = { views = "data/views" }

[stages.parts]
kind = "parts"
protected = ["eyes", 3]
inputs = { mesh = "outer.mesh", labels = "data/skin.obj" }

[stages.gen]
kind = "synthetic_scene"
size = "quick"
jitter_deg = -inf
[stages.gen.parts.torso]
length_cm = nan
"#;
    s.write("p.toml", bad.as_bytes());
    let out = s.fure(&["run", "p.toml", "--plain"]);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(2), "{err}");
    for want in [
        "p.toml:4:1: error: stage `outer`: parameter `voxel_pixels`: expected finite numbers only, found NaN",
        "p.toml:5:1: error: stage `outer`: parameter `mask_threshold`: 0 is below the minimum 0.01",
        "p.toml:6:1: error: stage `outer`: parameter `resolution`: -5 is below the minimum 8",
        "p.toml:7:1: error: stage `outer`: parameter `min_views_outside`: expected integer, found float (inf)",
        "p.toml:12:1: error: stage `parts`: parameter `protected`: expected array of strings",
        "p.toml:18:1: error: stage `gen`: parameter `jitter_deg`: expected finite numbers only, found -inf",
        "stage `gen`: parameter `parts`: `torso.length_cm`: expected finite numbers only, found NaN",
    ] {
        assert!(err.contains(want), "missing `{want}` in:\n{err}");
    }
    assert!(!s.path("out/p").exists(), "nothing may run");
    assert_eq!(s.entries("p", "outer"), 0);

    // `--set` values are checked the same way, located at the option.
    s.write("p.toml", HULL.as_bytes());
    s.fails_with(
        &["run", "p.toml", "--set", "outer.voxel_pixels=inf"],
        "p.toml",
        "outer",
        &["--set outer.voxel_pixels=inf: error: stage `outer`: parameter `voxel_pixels`: expected finite numbers only, found inf"],
    );
    s.fails_with(
        &["run", "p.toml", "--set", "outer.refine_steps=-1"],
        "p.toml",
        "outer",
        &["parameter `refine_steps`: -1 is below the minimum 0"],
    );
    // Positive-only parameters say so.
    s.write(
        "l.toml",
        b"[stages.l]\nkind = \"lengths\"\ns_cm = 0.0\ninputs = { outer = \"data/skin.obj\" }\n",
    );
    let out = s.fure(&["run", "l.toml"]);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        err.contains("l.toml:3:1: error: stage `l`: parameter `s_cm`: 0 is not allowed: expected a number greater than 0"),
        "{err}"
    );
    // Fixed: the same command runs.
    s.succeeds("p.toml");
}

// ---------------------------------------------------------------- images

#[test]
fn missing_truncated_and_garbage_images_name_the_file() {
    let s = Scene::new();
    let img = "data/views/train/002.png";
    let mask = "data/views/train/003_mask.png";
    let good_img = s.read(img);
    let good_mask = s.read(mask);

    // Missing image.
    std::fs::remove_file(s.path(img)).unwrap();
    s.fails(
        "hull.toml",
        "outer",
        &[
            "stage `outer` (outer_surface) failed",
            "train/002.png",
            "No such file",
        ],
    );
    // Truncated image: the position is the byte where decoding stopped.
    s.write(img, &good_img[..good_img.len() / 2]);
    s.fails("hull.toml", "outer", &["train/002.png: byte ", "PNG"]);
    // Not a PNG at all.
    s.write(img, b"GIF89a this is not a png");
    s.fails("hull.toml", "outer", &["train/002.png", "PNG"]);
    s.write(img, &good_img);

    // Truncated mask.
    s.write(mask, &good_mask[..60]);
    s.fails("hull.toml", "outer", &["train/003_mask.png: byte ", "PNG"]);
    // A mask of the wrong size.
    let small = {
        let p = s.path("small.png");
        fure_stages::formats::images::write_png(
            &p,
            &fure_stages::data::image::ImageF32::new(8, 8, 1),
        )
        .unwrap();
        std::fs::read(p).unwrap()
    };
    s.write(mask, &small);
    s.fails(
        "hull.toml",
        "outer",
        &[
            "train/003_mask.png",
            "mask is 8 x 8 but its image is 48 x 48",
        ],
    );
    s.write(mask, &good_mask);
    s.succeeds("hull.toml");
}

#[test]
fn truncated_and_garbage_exr_views_name_the_file() {
    // A capture may store its images as EXR: convert one training view (RGBA,
    // alpha = mask) and point its frame at it.
    let s = Scene::new();
    let png = fure_stages::formats::images::read_png(s.path("data/views/train/001.png")).unwrap();
    let exr_path = s.path("data/views/train/001.exr");
    fure_stages::formats::images::write_exr(&exr_path, &png).unwrap();
    let good_exr = std::fs::read(&exr_path).unwrap();
    let mut tf = json(&s.read("data/views/transforms.json"));
    tf["frames"][1]["file_path"] = Json::from("train/001.exr");
    s.write("data/views/transforms.json", &pretty(&tf));
    std::fs::remove_file(s.path("data/views/train/001.png")).unwrap();
    s.succeeds("hull.toml");

    s.write("data/views/train/001.exr", &good_exr[..good_exr.len() / 3]);
    s.fails(
        "hull.toml",
        "outer",
        &[
            "stage `outer` (outer_surface) failed",
            "train/001.exr: byte ",
            "EXR",
        ],
    );
    s.write("data/views/train/001.exr", b"\x76\x2f\x31\x01garbage");
    s.fails("hull.toml", "outer", &["train/001.exr", "EXR"]);
    s.write("data/views/train/001.exr", &good_exr);
    s.succeeds("hull.toml");
}

// ---------------------------------------------------------------- transforms.json

#[test]
fn broken_transforms_json_names_the_field() {
    let s = Scene::new();
    let file = "data/views/transforms.json";
    let good = s.read(file);
    let edit = |f: &dyn Fn(&mut Json)| {
        let mut v = json(&good);
        f(&mut v);
        s.write(file, &pretty(&v));
    };
    edit(&|v| {
        v["frames"][1]
            .as_object_mut()
            .unwrap()
            .remove("transform_matrix");
    });
    s.fails(
        "hull.toml",
        "outer",
        &["transforms.json: field `frames[1].transform_matrix`: missing"],
    );
    edit(&|v| v["frames"][2]["transform_matrix"][0][1] = Json::from("x"));
    s.fails(
        "hull.toml",
        "outer",
        &["transforms.json: field `frames[2].transform_matrix[0][1]`: expected a finite number, found a string"],
    );
    edit(&|v| v["frames"][0]["file_path"] = Json::from(5));
    s.fails(
        "hull.toml",
        "outer",
        &["transforms.json: field `frames[0].file_path`: expected a non-empty string, found a number"],
    );
    edit(&|v| v["frames"] = Json::from("all of them"));
    s.fails(
        "hull.toml",
        "outer",
        &["transforms.json: field `frames`: expected an array of frame objects"],
    );
    edit(&|v| v["fl_x"] = Json::from(-3.0));
    s.fails(
        "hull.toml",
        "outer",
        &["transforms.json: field `fl_x`: expected a positive value, found -3"],
    );
    // An unreadable frame path.
    edit(&|v| v["frames"][3]["file_path"] = Json::from("train/nope.png"));
    s.fails(
        "hull.toml",
        "outer",
        &[
            "train/nope.png",
            "No such file",
            "missing image: a frame of the transforms file lists `file_path` = `train/nope.png`",
        ],
    );
    // Truncated.
    s.write(file, &good[..good.len() / 2]);
    s.fails(
        "hull.toml",
        "outer",
        &["transforms.json: line ", "EOF while parsing"],
    );
    // NaN is not JSON; 1e999 overflows: both are located.
    let text = String::from_utf8(good.clone()).unwrap();
    let at = text.find("\"transform_matrix\"").unwrap();
    let first = at + text[at..].find("[\n").unwrap() + 1;
    let first = first + text[first..].find('[').unwrap() + 1;
    let end = first + text[first..].find(',').unwrap();
    s.write(
        file,
        format!("{}NaN{}", &text[..first], &text[end..]).as_bytes(),
    );
    s.fails("hull.toml", "outer", &["transforms.json: line ", "column"]);
    s.write(
        file,
        format!("{}1e999{}", &text[..first], &text[end..]).as_bytes(),
    );
    s.fails(
        "hull.toml",
        "outer",
        &["transforms.json: line ", "out of range"],
    );
    // Missing altogether.
    std::fs::remove_file(s.path(file)).unwrap();
    s.fails(
        "hull.toml",
        "outer",
        &[
            "data/views",
            "expected transforms.json or transforms_train.json",
        ],
    );
    s.write(file, &good);
    s.succeeds("hull.toml");
}

// ---------------------------------------------------------------- cameras and masks

/// The scene's `transforms.json` with the given columns (camera axes) of every frame's
/// camera-to-world matrix negated.
fn with_camera_axes_negated(good: &[u8], columns: [usize; 2]) -> Vec<u8> {
    let mut v = json(good);
    for f in v["frames"].as_array_mut().unwrap() {
        let m = &mut f["transform_matrix"];
        for r in 0..3 {
            for c in columns {
                let x = m[r][c].as_f64().unwrap();
                m[r][c] = Json::from(-x);
            }
        }
    }
    pretty(&v)
}

#[test]
fn cameras_looking_away_give_an_empty_visual_hull() {
    let s = Scene::new();
    let file = "data/views/transforms.json";
    let good = s.read(file);
    // Turn every camera around its own up axis (negate its x and z axes).
    s.write(file, &with_camera_axes_negated(&good, [0, 2]));
    let err = s.fails(
        "hull.toml",
        "outer",
        &[
            "no camera sees the object",
            "the visual hull is empty",
            "data/views/transforms.json",
        ],
    );
    // Turned around, not written with OpenCV's axes: no hint that they are.
    assert!(!err.contains("OpenCV"), "{err}");
    s.write(file, &good);
    s.succeeds("hull.toml");
}

#[test]
fn cameras_written_with_opencv_axes_are_named_as_such() {
    let s = Scene::new();
    let file = "data/views/transforms.json";
    let good = s.read(file);
    // Camera-to-world matrices with OpenCV's camera axes (+z forward, +y down): the y and z
    // columns negated.
    s.write(file, &with_camera_axes_negated(&good, [1, 2]));
    s.fails(
        "hull.toml",
        "outer",
        &[
            "the visual hull is empty",
            "data/views/transforms.json",
            "the cameras look like OpenCV's",
            "negate the second and third columns",
        ],
    );
    s.write(file, &good);
    s.succeeds("hull.toml");
}

#[test]
fn an_empty_mask_names_the_mask_file() {
    let s = Scene::new();
    let mask = "data/views/train/004_mask.png";
    let good = s.read(mask);
    let empty = {
        let p = s.path("empty.png");
        fure_stages::formats::images::write_png(
            &p,
            &fure_stages::data::image::ImageF32::new(48, 48, 1),
        )
        .unwrap();
        std::fs::read(p).unwrap()
    };
    s.write(mask, &empty);
    s.fails(
        "hull.toml",
        "outer",
        &[
            "train/004_mask.png",
            "the mask has no foreground pixel above 0.5",
        ],
    );
    s.write(mask, &good);
    s.succeeds("hull.toml");
}

// ---------------------------------------------------------------- meshes

/// A closed outer mesh (the visual hull of the scene) as the user's OBJ.
fn with_outer_obj(s: &Scene) -> String {
    s.succeeds("hull.toml");
    let obj = s.text("out/hull/outer/mesh.obj");
    s.write("data/outer.obj", obj.as_bytes());
    s.write("import.toml", IMPORT.as_bytes());
    s.write("parts.toml", PARTS.as_bytes());
    obj
}

/// Rewrites every `f a b c` line with `f(corners)`; other lines are kept.
fn map_faces(obj: &str, f: impl Fn(usize, Vec<&str>) -> Option<Vec<String>>) -> String {
    let mut out = String::new();
    let mut k = 0;
    for line in obj.lines() {
        if let Some(rest) = line.strip_prefix("f ") {
            if let Some(c) = f(k, rest.split_whitespace().collect()) {
                out.push_str(&format!("f {}\n", c.join(" ")));
            }
            k += 1;
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

#[test]
fn inside_out_meshes_are_flipped_with_a_warning_and_broken_ones_refused() {
    let s = Scene::new();
    let good = with_outer_obj(&s);
    for (pipeline, stage) in [("import.toml", "outer"), ("parts.toml", "parts")] {
        // Inside-out: every face reversed -> fixed, with a warning in metrics.json.
        let flipped = map_faces(&good, |_, c| {
            Some(c.iter().rev().map(|x| x.to_string()).collect())
        });
        s.write("data/outer.obj", flipped.as_bytes());
        let stdout = s.succeeds(pipeline);
        assert!(stdout.contains("inside-out"), "{stdout}");
        let name = pipeline.trim_end_matches(".toml");
        let m = json(&s.read(&format!("out/{name}/{stage}/metrics.json")));
        let w = m["warnings"].as_array().unwrap();
        assert_eq!(w.len(), 1, "{m}");
        assert!(w[0].as_str().unwrap().contains("inside-out"), "{m}");
        // The stage's output is outward again: the same as from the good file.
        s.write("data/outer.obj", good.as_bytes());
        s.succeeds(pipeline);
        let m = json(&s.read(&format!("out/{name}/{stage}/metrics.json")));
        assert_eq!(m["warnings"].as_array().unwrap().len(), 0, "{m}");

        // A hole: drop one face.
        let holed = map_faces(&good, |k, c| {
            (k != 10).then(|| c.iter().map(|x| x.to_string()).collect())
        });
        s.write("data/outer.obj", holed.as_bytes());
        s.fails(
            pipeline,
            stage,
            &[
                "data/outer.obj",
                "not watertight: 3 boundary edges",
                "expected a closed surface",
            ],
        );
        // A fin: a face repeated twice more makes its edges shared by 3 faces... and 4.
        let mut finned = good.clone();
        let face = good
            .lines()
            .find(|l| l.starts_with("f "))
            .unwrap()
            .to_string();
        finned.push_str(&format!("{face}\n{face}\n"));
        s.write("data/outer.obj", finned.as_bytes());
        s.fails(
            pipeline,
            stage,
            &[
                "data/outer.obj",
                "non-manifold: 3 edges are shared by more than two triangles",
                "expected each edge shared by exactly two",
            ],
        );
        // Truncated in the middle of the faces: holes again, or a broken last line.
        let cut = good.len() - good.len() / 7;
        s.write("data/outer.obj", &good.as_bytes()[..cut]);
        s.fails(pipeline, stage, &["data/outer.obj"]);
        // Fixed: runs again.
        s.write("data/outer.obj", good.as_bytes());
        s.succeeds(pipeline);
    }
}

#[test]
fn malformed_obj_files_name_line_and_column() {
    let s = Scene::new();
    let good = s.text("data/skin.obj");
    let first_v = good.find("\nv ").unwrap() + 1;
    let line_no = good[..first_v].lines().count() + 1;
    let replace_first_v = |with: &str| {
        let end = first_v + good[first_v..].find('\n').unwrap();
        format!("{}{}{}", &good[..first_v], with, &good[end..])
    };
    s.write("data/skin.obj", replace_first_v("v 0.1 x 0.3").as_bytes());
    s.fails(
        "hull.toml",
        "parts",
        &[
            "stage `parts` (parts) failed",
            &format!("data/skin.obj): line {line_no}, column 7: expected a finite number for y, found `x`"),
        ],
    );
    s.write("data/skin.obj", format!("{good}f 1 2 999999\n").as_bytes());
    s.fails("hull.toml", "parts", &["data/skin.obj", "999999"]);
    s.write("data/skin.obj", format!("{good}f 1//1 2//").as_bytes());
    s.fails(
        "hull.toml",
        "parts",
        &["data/skin.obj", "a face needs at least 3 vertices, found 2"],
    );
    s.write("data/skin.obj", good.as_bytes());
    s.succeeds("hull.toml");
}

#[test]
fn a_mesh_without_fur_parts_is_an_error_of_parts() {
    let s = Scene::new();
    let skin = s.text("data/skin.obj");
    let names: Vec<String> = skin
        .lines()
        .filter_map(|l| l.strip_prefix("g "))
        .map(|n| format!("{:?}", n.trim()))
        .collect();
    assert!(names.len() > 3, "{names:?}");
    // Every part protected.
    let all = format!("{HULL}protected = [{}]\n", names.join(", "));
    s.write("all.toml", all.as_bytes());
    s.fails(
        "all.toml",
        "parts",
        &[
            "data/skin.obj",
            "the mesh has no fur parts: every vertex is in a protected part",
            "expected at least one part that is not in the `protected` parameter",
        ],
    );
    // Fixed (the default protected set): runs.
    s.succeeds("hull.toml");
    // A label source with one non-fur group only.
    let mut eyes_only = String::from("g eyes\n");
    eyes_only.push_str(
        &skin
            .lines()
            .filter(|l| !l.starts_with("g ") && !l.starts_with('#'))
            .collect::<Vec<_>>()
            .join("\n"),
    );
    s.write("data/skin.obj", eyes_only.as_bytes());
    s.fails(
        "hull.toml",
        "parts",
        &["data/skin.obj", "the mesh has no fur parts"],
    );
    s.write("data/skin.obj", skin.as_bytes());
    s.succeeds("hull.toml");
}

// ---------------------------------------------------------------- NaN in inputs

#[test]
fn nan_in_inputs_fails_clearly_and_writes_nothing() {
    let s = Scene::new();
    // An OBJ vertex `v nan 0 0` in the user's mesh.
    s.write("import.toml", IMPORT.as_bytes());
    let skin = s.text("data/skin.obj");
    let first_v = skin.find("\nv ").unwrap() + 1;
    let end = first_v + skin[first_v..].find('\n').unwrap();
    let nan_obj = format!("{}v nan 0 0{}", &skin[..first_v], &skin[end..]);
    s.write("data/outer.obj", nan_obj.as_bytes());
    s.fails(
        "import.toml",
        "outer",
        &[
            "stage `outer` (outer_surface) failed",
            "data/outer.obj",
            "expected a finite number for x, found `nan`",
        ],
    );
    assert!(
        !s.path("out/import/outer").exists(),
        "a failing stage wrote outputs"
    );
    assert!(!s.path("out/import/parts").exists());
    // A transform matrix entry that overflows to infinity.
    let tf = s.text("data/views/transforms.json");
    let at = tf.find("\"transform_matrix\"").unwrap();
    let num_start = at
        + tf[at..]
            .find(|c: char| c == '-' || c.is_ascii_digit())
            .unwrap();
    let num_end = num_start + tf[num_start..].find(',').unwrap();
    s.write(
        "data/views/transforms.json",
        format!("{}-1e400{}", &tf[..num_start], &tf[num_end..]).as_bytes(),
    );
    s.fails("hull.toml", "outer", &["data/views/transforms.json: line "]);
    assert!(
        !s.path("out/hull").exists(),
        "a failing stage wrote outputs"
    );
    // Fixed: both run.
    s.write("data/views/transforms.json", tf.as_bytes());
    s.succeeds("hull.toml");
    s.write(
        "data/outer.obj",
        s.read("out/hull/outer/mesh.obj").as_slice(),
    );
    s.succeeds("import.toml");
}

// ---------------------------------------------------------------- fuzzing the pipeline parser

/// Property-based fuzzing of the pipeline parser and planner (proptest): from
/// arbitrary bytes, from token soup in TOML's vocabulary, from mutations of
/// the shipped pipelines, and from generated pipelines whose stages are real
/// kinds with arbitrary parameter values (so every stage's `validate`,
/// `inputs` and `outputs` see hostile values). The property: no panic, and
/// every error carries a location in the file (or the `--set` option).
/// `PROPTEST_CASES` sets the number of cases (default 64 for CI).
mod fuzz {
    use std::path::Path;

    use fure::pipeline::{parse_cli_list, parse_cli_value, Pipeline, PipelineErrors};
    use fure::plan::{plan, Registry};
    use proptest::prelude::*;
    use proptest::test_runner::Config;

    fn config() -> Config {
        let cases = std::env::var("PROPTEST_CASES")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(64);
        Config {
            cases,
            failure_persistence: None,
            // The short default run (CI) is reproducible: a fixed seed unless a long run
            // (`PROPTEST_CASES`) or `PROPTEST_RNG_SEED` asks for other inputs.
            rng_seed: ci_seed(),
            ..Config::default()
        }
    }

    /// A fixed seed for the default run; proptest's own choice (random, or `PROPTEST_RNG_SEED`) for
    /// long runs.
    fn ci_seed() -> proptest::test_runner::RngSeed {
        if std::env::var_os("PROPTEST_CASES").is_none()
            && std::env::var_os("PROPTEST_RNG_SEED").is_none()
        {
            proptest::test_runner::RngSeed::Fixed(0x5eed)
        } else {
            Config::default().rng_seed
        }
    }

    fn registry() -> &'static Registry {
        static R: std::sync::OnceLock<Registry> = std::sync::OnceLock::new();
        R.get_or_init(|| Registry::new(fure_stages::registry()).unwrap())
    }

    /// Every error is located in `f.toml` (line >= 1) or at a `--set`.
    fn located(e: &PipelineErrors, text: &str) -> Result<(), TestCaseError> {
        prop_assert!(!e.0.is_empty());
        let lines = text.lines().count() + 1;
        for err in &e.0 {
            let Some(loc) = &err.loc else {
                return Err(TestCaseError::fail(format!(
                    "error without a location: {err}"
                )));
            };
            if loc.file.starts_with("--set") {
                continue;
            }
            prop_assert_eq!(&*loc.file, "f.toml", "{}", err);
            prop_assert!(
                loc.line <= lines.max(1),
                "line {} past the end ({} lines): {}",
                loc.line,
                lines,
                err
            );
            prop_assert!(!err.message.is_empty());
        }
        Ok(())
    }

    /// Parses and, when that succeeds, plans `text`.
    fn parse_and_plan(text: &str, sets: &[String]) -> Result<(), TestCaseError> {
        let dir = Path::new("/nonexistent-fure-fuzz");
        match Pipeline::parse_str(text, "f.toml", dir) {
            Err(e) => located(&e, text),
            Ok(mut p) => {
                let mut errs = Vec::new();
                for s in sets {
                    if let Err(e) = p.apply_set(s, "--set") {
                        errs.push(e);
                    }
                }
                if !errs.is_empty() {
                    return located(&PipelineErrors(errs), text);
                }
                match plan(&p, registry()) {
                    Ok(pl) => {
                        prop_assert_eq!(pl.stages.len(), p.stages.len());
                        Ok(())
                    }
                    Err(e) => located(&e, text),
                }
            }
        }
    }

    const TOML_WORDS: &[&str] = &[
        "[stages.a]",
        "[stages.b]",
        "[stages.a.parts.torso]",
        "[[stages.a.x]]",
        "[pipeline]",
        "[sweep]",
        "kind",
        "=",
        "\"outer_surface\"",
        "\"parts\"",
        "\"synthetic_scene\"",
        "\"command\"",
        "inputs",
        "{",
        "}",
        "[",
        "]",
        ",",
        ".",
        "\"a.mesh\"",
        "\"b.mesh\"",
        "views",
        "mesh",
        "extends",
        "name",
        "nan",
        "inf",
        "-inf",
        "1e400",
        "-0",
        "0",
        "9223372036854775807",
        "-9223372036854775808",
        "1979-05-27",
        "true",
        "\"\"",
        "'x'",
        "\"\"\"",
        "'''",
        "#",
        "\n",
        "\r\n",
        "\\",
        "\"\\u0000\"",
        "é",
        "\t",
        "deps",
        "cmd",
        "outs",
        "voxel_pixels",
        "resolution",
        "protected",
        "preset",
        "size",
        "\"quick\"",
    ];

    fn token_soup() -> impl Strategy<Value = String> {
        proptest::collection::vec(
            prop_oneof![
                4 => (0..TOML_WORDS.len()).prop_map(|i| TOML_WORDS[i].to_string()),
                1 => any::<i64>().prop_map(|i| i.to_string()),
                1 => any::<f64>().prop_map(|f| f.to_string()),
                1 => "[a-z_.]{1,8}",
            ],
            0..60,
        )
        .prop_map(|t| t.join(" "))
    }

    /// The shipped pipelines and this test file's own: near-valid starting points.
    fn seeds() -> Vec<String> {
        let mut v = vec![
            super::HULL.to_string(),
            super::IMPORT.to_string(),
            super::GEN.to_string(),
        ];
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines");
        if let Ok(rd) = std::fs::read_dir(dir) {
            let mut files: Vec<_> = rd.filter_map(|e| e.ok()).map(|e| e.path()).collect();
            files.sort();
            for f in files {
                if f.extension().is_some_and(|e| e == "toml") {
                    if let Ok(t) = std::fs::read_to_string(&f) {
                        // `extends` is not allowed in parse_str; keep the rest.
                        v.push(
                            t.lines()
                                .filter(|l| !l.trim_start().starts_with("extends"))
                                .collect::<Vec<_>>()
                                .join("\n"),
                        );
                    }
                }
            }
        }
        v
    }

    #[derive(Debug, Clone)]
    enum Edit {
        Delete(usize, usize),
        Insert(usize, String),
        Replace(usize, String),
        Truncate(usize),
    }

    fn edits() -> impl Strategy<Value = Vec<Edit>> {
        let word = (0..TOML_WORDS.len()).prop_map(|i| TOML_WORDS[i].to_string());
        proptest::collection::vec(
            prop_oneof![
                (any::<usize>(), 1usize..20).prop_map(|(p, n)| Edit::Delete(p, n)),
                (any::<usize>(), word.clone()).prop_map(|(p, w)| Edit::Insert(p, w)),
                (any::<usize>(), word).prop_map(|(p, w)| Edit::Replace(p, w)),
                any::<usize>().prop_map(Edit::Truncate),
            ],
            1..5,
        )
    }

    /// Applies edits on char boundaries (the parser gets `&str`).
    fn apply(text: &str, edits: &[Edit]) -> String {
        let mut chars: Vec<char> = text.chars().collect();
        for e in edits {
            let n = chars.len();
            let at = |p: usize| if n == 0 { 0 } else { p % (n + 1) };
            match e {
                Edit::Delete(p, k) if n > 0 => {
                    let i = p % n;
                    chars.drain(i..(i + k).min(n));
                }
                Edit::Insert(p, w) => {
                    let i = at(*p);
                    chars.splice(i..i, w.chars());
                }
                Edit::Replace(p, w) => {
                    // Replace the word (run of non-space chars) around p.
                    let i = at(*p);
                    let s = chars[..i]
                        .iter()
                        .rposition(|c| c.is_whitespace())
                        .map_or(0, |k| k + 1);
                    let t = chars[i..]
                        .iter()
                        .position(|c| c.is_whitespace())
                        .map_or(n, |k| i + k);
                    chars.splice(s..t, w.chars());
                }
                Edit::Truncate(p) => chars.truncate(at(*p)),
                _ => {}
            }
        }
        chars.into_iter().collect()
    }

    /// A parameter value in TOML: numbers at the edges, wrong types, nested tables.
    fn toml_value() -> impl Strategy<Value = String> {
        let leaf = prop_oneof![
            Just("nan".to_string()),
            Just("inf".to_string()),
            Just("-inf".to_string()),
            Just("0".to_string()),
            Just("-1".to_string()),
            Just("0.0".to_string()),
            Just("1e300".to_string()),
            Just("9223372036854775807".to_string()),
            Just("-9223372036854775808".to_string()),
            Just("true".to_string()),
            Just("\"\"".to_string()),
            Just("\"quick\"".to_string()),
            Just("\"tiger\"".to_string()),
            Just("\"fixed\"".to_string()),
            any::<i64>().prop_map(|i| i.to_string()),
            any::<f64>().prop_map(|f| format!("{f:?}")),
            "[a-z]{0,6}".prop_map(|s| format!("{s:?}")),
        ];
        leaf.prop_recursive(2, 12, 4, |inner| {
            prop_oneof![
                proptest::collection::vec(inner.clone(), 0..4)
                    .prop_map(|v| format!("[{}]", v.join(", "))),
                proptest::collection::vec(("[a-z_]{1,10}", inner), 0..4).prop_map(|kv| {
                    // A key twice in one inline table is a TOML error: keep the first.
                    let mut seen = std::collections::BTreeSet::new();
                    let body: Vec<String> = kv
                        .iter()
                        .filter(|(k, _)| seen.insert(k.clone()))
                        .map(|(k, v)| format!("{k} = {v}"))
                        .collect();
                    format!("{{ {} }}", body.join(", "))
                }),
            ]
        })
    }

    /// A value of the parameter's own type, at or near its bounds (or wild when it
    /// has none), so that it passes the type and bound checks and reaches the
    /// stage's `validate`, `inputs` and `outputs`.
    fn typed_value(spec: &fure_stage_api::ParamSpec, r: u64) -> String {
        use fure_stage_api::ParamType as T;
        let pick = |n: usize, k: u64| (r.rotate_left(k as u32 * 13) % n as u64) as usize;
        let lo = spec.min.unwrap_or(-1e30);
        let hi = spec.max.unwrap_or(1e30);
        let float = |k: u64| -> String {
            let cands = [
                lo,
                hi,
                0.0,
                1e-12,
                0.5,
                1.0,
                3.7,
                1e6,
                -2.0,
                f64::MIN_POSITIVE,
            ];
            let x = cands[pick(cands.len(), k)].clamp(lo, hi);
            let x = if spec.min_exclusive && x <= lo {
                lo + 1e-9
            } else {
                x
            };
            format!("{x:?}")
        };
        let int = |k: u64| -> String {
            let cands = [lo, hi, 0.0, 1.0, 2.0, 3.0, 7.0, 100.0, 65536.0, 1e9, 9.2e18];
            let x = cands[pick(cands.len(), k)]
                .clamp(lo.max(-9.2e18), hi.min(9.2e18))
                .round();
            format!("{}", x as i64)
        };
        const WORDS: &[&str] = &[
            "", "x", "tiger", "fixed", "quick", "torso", "eyes", "a.b", "../..", "/", "é", " ",
        ];
        let string = |k: u64| -> String {
            if !spec.choices.is_empty() && pick(4, k) > 0 {
                format!("{:?}", spec.choices[pick(spec.choices.len(), k + 1)])
            } else {
                format!("{:?}", WORDS[pick(WORDS.len(), k + 2)])
            }
        };
        match spec.ty {
            T::Bool => r.is_multiple_of(2).to_string(),
            T::Int => int(1),
            T::Float => float(1),
            T::Str => string(1),
            T::FloatList => {
                let n = pick(5, 3);
                format!(
                    "[{}]",
                    (0..n)
                        .map(|k| float(k as u64 + 4))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            }
            T::StrList => {
                let n = pick(4, 3);
                format!(
                    "[{}]",
                    (0..n)
                        .map(|k| string(k as u64 + 4))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            }
            T::Table => {
                // Per-part overrides: part names, then fields of several types.
                const KEYS: &[&str] = &[
                    "torso",
                    "head",
                    "tail",
                    "eyes",
                    "nope",
                    "length_cm",
                    "density",
                    "color",
                    "curl",
                    "clump",
                    "gravity",
                    "direction",
                    "lift_deg",
                    "length_jitter",
                    "density_per_cm2",
                    "multiplier",
                    "thickness_cm",
                ];
                const VALS: &[&str] = &[
                    "0",
                    "-1",
                    "0.0",
                    "1e30",
                    "-1e30",
                    "0.5",
                    "2",
                    "\"x\"",
                    "true",
                    "[]",
                    "[0.1, 0.2, 0.3]",
                    "[1, 2]",
                    "[\"a\"]",
                    "{}",
                    "9223372036854775807",
                ];
                let parts = pick(3, 5);
                let mut t = Vec::new();
                for p in 0..parts {
                    let fields = pick(4, 6 + p as u64);
                    let mut inner = std::collections::BTreeSet::new();
                    let body: Vec<String> = (0..fields)
                        .filter_map(|f| {
                            let k = KEYS[pick(KEYS.len(), 7 + p as u64 * 5 + f as u64)];
                            let v = VALS[pick(VALS.len(), 9 + p as u64 * 7 + f as u64)];
                            // A key twice in one inline table is a TOML error: keep the first.
                            inner.insert(k).then(|| format!("{k} = {v}"))
                        })
                        .collect();
                    let key = KEYS[pick(KEYS.len(), 11 + p as u64)];
                    if pick(3, 12 + p as u64) == 0 {
                        t.push(format!("{key} = {}", VALS[pick(VALS.len(), 13 + p as u64)]));
                    } else {
                        t.push(format!("{key} = {{ {} }}", body.join(", ")));
                    }
                }
                // Duplicate keys are a TOML error: keep the first of each.
                let mut seen = std::collections::BTreeSet::new();
                t.retain(|kv| seen.insert(kv.split(" = ").next().unwrap_or("").to_string()));
                format!("{{ {} }}", t.join(", "))
            }
        }
    }

    /// A pipeline of real stage kinds with values for their real parameters:
    /// mostly of the right type near the bounds, sometimes anything at all.
    fn generated_pipeline() -> impl Strategy<Value = String> {
        let kinds: Vec<(&'static str, Vec<fure_stage_api::ParamSpec>)> =
            registry().iter().map(|s| (s.kind(), s.params())).collect();
        let n = kinds.len();
        proptest::collection::vec(
            (
                0..n,
                proptest::collection::vec(
                    (
                        any::<prop::sample::Index>(),
                        toml_value(),
                        any::<u64>(),
                        0u8..4,
                    ),
                    0..8,
                ),
            ),
            1..4,
        )
        .prop_map(move |stages| {
            let mut out = String::new();
            for (i, (k, params)) in stages.iter().enumerate() {
                let (kind, specs) = &kinds[*k];
                out.push_str(&format!("[stages.s{i}]\nkind = \"{kind}\"\n"));
                let mut seen = std::collections::BTreeSet::new();
                for (idx, wild, r, mode) in params {
                    if specs.is_empty() {
                        break;
                    }
                    let spec = &specs[idx.index(specs.len())];
                    if seen.insert(spec.name) {
                        let v = if *mode == 0 {
                            wild.clone()
                        } else {
                            typed_value(spec, *r)
                        };
                        out.push_str(&format!("{} = {v}\n", spec.name));
                    }
                }
                if i > 0 {
                    out.push_str(&format!("inputs = {{ mesh = \"s{}.mesh\" }}\n", i - 1));
                }
            }
            out
        })
    }

    /// The generator is not vacuous: a fair share of its pipelines get past the
    /// parameter checks and `validate` of every stage (they plan, or fail only on
    /// inputs and ports, which are checked after `validate`).
    #[test]
    fn generated_pipelines_reach_validate() {
        use proptest::strategy::ValueTree;
        let mut runner = proptest::test_runner::TestRunner::deterministic();
        let strat = generated_pipeline();
        let (mut past, total) = (0, 300);
        for _ in 0..total {
            let text = strat.new_tree(&mut runner).unwrap().current();
            let p = Pipeline::parse_str(&text, "f.toml", Path::new("/nonexistent")).unwrap();
            match plan(&p, registry()) {
                Ok(_) => past += 1,
                Err(e) => {
                    let late = [
                        "missing input",
                        "has no input port",
                        "neither an output",
                        "has no output",
                        "expects a",
                    ];
                    if e.0
                        .iter()
                        .all(|x| late.iter().any(|l| x.message.contains(l)))
                    {
                        past += 1;
                    }
                }
            }
        }
        assert!(
            past * 5 >= total,
            "only {past} of {total} generated pipelines reached validate"
        );
    }

    /// Every default passes its own type and bounds, and every numeric parameter
    /// of a reconstruction stage states its lower bound (a zero or negative value
    /// is then a planning error with a location, not a NaN three stages later).
    #[test]
    fn parameter_specs_are_bounded_and_defaults_valid() {
        use fure_stage_api::ParamType as T;
        let mut unbounded = Vec::new();
        for stage in registry().iter() {
            for spec in stage.params() {
                if let Some(d) = &spec.default {
                    if let Err(e) = fure::plan::check_value(&spec, d) {
                        panic!("{}.{}: default {d:?}: {e}", stage.kind(), spec.name);
                    }
                }
                let numeric = matches!(spec.ty, T::Int | T::Float | T::FloatList);
                let exempt = stage.kind().starts_with("demo_") || stage.kind() == "command";
                if numeric && spec.min.is_none() && !exempt {
                    unbounded.push(format!("{}.{}", stage.kind(), spec.name));
                }
            }
        }
        assert!(
            unbounded.is_empty(),
            "numeric parameters without a lower bound: {unbounded:?}"
        );
    }

    #[test]
    fn seeds_plan_or_fail_located() {
        for s in seeds() {
            parse_and_plan(&s, &[]).unwrap();
        }
    }

    proptest! {
        #![proptest_config(config())]

        #[test]
        fn fuzz_pipeline_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            parse_and_plan(&String::from_utf8_lossy(&bytes), &[])?;
        }

        #[test]
        fn fuzz_pipeline_tokens(text in token_soup()) {
            parse_and_plan(&text, &[])?;
        }

        #[test]
        fn fuzz_pipeline_mutations(seed in any::<prop::sample::Index>(), e in edits()) {
            let seeds = seeds();
            let text = apply(&seeds[seed.index(seeds.len())], &e);
            parse_and_plan(&text, &[])?;
        }

        #[test]
        fn fuzz_pipeline_generated(text in generated_pipeline(), set in "[a-z0-9_.=\\[\\], -]{0,24}") {
            parse_and_plan(&text, &[])?;
            // The same pipeline with an arbitrary --set on top.
            let _ = parse_cli_value(&set);
            let _ = parse_cli_list(&set);
            parse_and_plan(&text, &[format!("s0.{set}")])?;
        }
    }
}
