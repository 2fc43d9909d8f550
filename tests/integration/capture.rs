//! A user's own capture: a labelled mesh in the wrong frame is refused with its cause named, on
//! every synthetic preset the right one passes; COLMAP sparse models (text and binary) with
//! `images/` and `masks/` are read as views by the stages that read transforms.json.

use std::path::Path;

use serde_json::Value as Json;

use crate::engine::Project;

/// The synthetic scene at its smallest, its visual hull and the label transfer from its
/// `labels.obj` (the GT skin's part groups: a fur thickness inside M_outer).
const LABELS: &str = r#"
[pipeline]
name = "labels"

[stages.scene]
kind = "synthetic_scene"
size = "quick"
views = 8
test_views = 1
resolution = 64
supersample = 1

[stages.outer]
kind = "outer_surface"
inputs = { views = "scene.views" }

[stages.parts]
kind = "parts"
inputs = { mesh = "outer.mesh", labels = "scene.labels" }
"#;

fn read_json(path: &Path) -> Json {
    serde_json::from_slice(&std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// An OBJ's text with every `v` and `vn` line mapped through `f`.
fn map_obj(text: &str, f: impl Fn([f64; 3]) -> [f64; 3]) -> String {
    let mut out = String::new();
    for line in text.lines() {
        let mut w = line.split_whitespace();
        match w.next() {
            Some(tag @ ("v" | "vn")) => {
                let v: Vec<f64> = w.map(|x| x.parse().unwrap()).collect();
                let m = f([v[0], v[1], v[2]]);
                out.push_str(&format!("{tag} {} {} {}\n", m[0], m[1], m[2]));
            }
            _ => {
                out.push_str(line);
                out.push('\n');
            }
        }
    }
    out
}

#[test]
fn label_meshes_in_the_wrong_frame_fail_and_every_preset_passes() {
    let p = Project::new();
    p.write("labels.toml", LABELS);
    // The tiger last: its outputs stay in out/labels for the cases below.
    for preset in ["fox", "cat", "panda", "bison", "wolf", "tiger"] {
        let set = format!("scene.preset={preset}");
        p.run("labels.toml", &["--set", &set]).ok();
        let m = read_json(&p.path("out/labels/parts/metrics.json"));
        let a = &m["alignment"];
        eprintln!("{preset}: {a}");
        let num = |k: &str| a[k].as_f64().unwrap_or_else(|| panic!("{preset}: alignment.{k} in {m}"));
        // Margins: the synthetic skin sits well inside every limit.
        assert!((0.6..1.2).contains(&num("size_ratio")), "{preset}: {a}");
        assert!(num("mean_distance_frac") < 0.5 * 0.08, "{preset}: {a}");
        assert!(num("outside_frac") < 0.5 * 0.2, "{preset}: {a}");
    }

    // The tiger's labels as Blender's default OBJ export would write them (Y-up), in centimetres,
    // and moved by half the animal's size: `parts` fails and names the cause.
    let labels = p.read("out/labels/scene/labels.obj");
    let outer = p.read("out/labels/outer/mesh.obj");
    let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
    for l in outer.lines().filter_map(|l| l.strip_prefix("v ")) {
        for (k, x) in l.split_whitespace().map(|x| x.parse::<f64>().unwrap()).enumerate() {
            lo[k] = lo[k].min(x);
            hi[k] = hi[k].max(x);
        }
    }
    let half: [f64; 3] = std::array::from_fn(|k| 0.5 * (hi[k] - lo[k]));
    let cases: [(&str, Box<dyn Fn([f64; 3]) -> [f64; 3]>, &[&str]); 3] = [
        ("yup", Box::new(|[x, y, z]| [x, z, -y]), &["rotated", "+90 degrees about X", "Y-up"]),
        ("cm", Box::new(|[x, y, z]| [100.0 * x, 100.0 * y, 100.0 * z]), &["~100x larger", "centimetres vs metres"]),
        ("moved", Box::new(move |[x, y, z]| [x + half[0], y + half[1], z + half[2]]), &["shifted"]),
    ];
    for (name, f, words) in cases {
        let file = format!("labels_{name}.obj");
        p.write(&file, &map_obj(&labels, f));
        p.write(
            &format!("{name}.toml"),
            &LABELS
                .replace("name = \"labels\"", &format!("name = \"{name}\""))
                .replace("scene.preset", "")
                .replace("labels = \"scene.labels\"", &format!("labels = \"{file}\"")),
        );
        let r = p.run(&format!("{name}.toml"), &["--set", "scene.preset=tiger"]);
        assert_ne!(r.code(), 0, "{name}: the misaligned labels passed");
        assert_eq!(r.status("parts"), "failed", "{name}: {:?}", r.stages);
        let text = format!("{}{}", r.stdout(), r.stderr());
        for w in words {
            assert!(text.contains(w), "{name}: no `{w}` in:\n{text}");
        }
        assert!(text.contains("labels"), "{name}: the input is not named:\n{text}");
    }
}
