//! A user's own capture: a labelled mesh in the wrong frame is refused with its cause named, on
//! every synthetic preset the right one passes; COLMAP sparse models (text and binary) with
//! `images/` and `masks/` are read as views by the stages that read transforms.json; a capture
//! rendered by Blender, with Blender's own hair, runs through `capture.toml` and is scored against
//! that hair.

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
    serde_json::from_slice(
        &std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    )
    .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// An OBJ's text with every `v` and `vn` line mapped through `f`.
pub(crate) fn map_obj(text: &str, f: impl Fn([f64; 3]) -> [f64; 3]) -> String {
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
        let num = |k: &str| {
            a[k].as_f64()
                .unwrap_or_else(|| panic!("{preset}: alignment.{k} in {m}"))
        };
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
        for (k, x) in l
            .split_whitespace()
            .map(|x| x.parse::<f64>().unwrap())
            .enumerate()
        {
            lo[k] = lo[k].min(x);
            hi[k] = hi[k].max(x);
        }
    }
    let half: [f64; 3] = std::array::from_fn(|k| 0.5 * (hi[k] - lo[k]));
    type Case = (
        &'static str,
        Box<dyn Fn([f64; 3]) -> [f64; 3]>,
        &'static [&'static str],
    );
    let cases: [Case; 3] = [
        (
            "yup",
            Box::new(|[x, y, z]| [x, z, -y]),
            &["rotated", "+90 degrees about X", "Y-up"],
        ),
        (
            "cm",
            Box::new(|[x, y, z]| [100.0 * x, 100.0 * y, 100.0 * z]),
            &["~100x larger", "centimetres vs metres"],
        ),
        (
            "moved",
            Box::new(move |[x, y, z]| [x + half[0], y + half[1], z + half[2]]),
            &["shifted"],
        ),
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
        assert!(
            text.contains("labels"),
            "{name}: the input is not named:\n{text}"
        );
    }
}

/// The synthetic tiger's views and the stages that read views, on either layout.
const HULL: &str = r#"
[pipeline]
name = "NAME"

[stages.outer]
kind = "outer_surface"
inputs = { views = "VIEWS" }

[stages.parts]
kind = "parts"
inputs = { mesh = "outer.mesh", labels = "labels.obj" }
"#;

/// Writes a 3-channel image as a JPEG (quality 95), as a camera or COLMAP's users would have it.
fn write_jpeg(path: &Path, rgb: &fure_stages::data::image::ImageF32) {
    assert_eq!(rgb.channels, 3);
    let bytes: Vec<u8> = rgb
        .data
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95)
        .encode(
            &bytes,
            rgb.width,
            rgb.height,
            image::ExtendedColorType::Rgb8,
        )
        .unwrap();
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, out).unwrap();
}

fn hull(p: &Project, name: &str, views: &str) -> crate::engine::Run {
    p.write(
        &format!("{name}.toml"),
        &HULL.replace("NAME", name).replace("VIEWS", views),
    );
    p.run(&format!("{name}.toml"), &[])
}

/// The synthetic views as a user's COLMAP capture: a sparse text model, JPEG photos (no alpha,
/// the animal in front of a light wall) under `images/`, masks under `masks/`. The visual hull
/// and the label transfer on it match those of the same training cameras written as
/// transforms.json, and the shipped `capture.toml` runs on it end to end (every stage that
/// reads the photos reads JPEG, and the learner sees the photos over black through the masks).
#[test]
fn colmap_capture_with_masks_folder_reads_like_transforms_json() {
    use fure_stages::formats::{cameras, colmap, images};
    let p = Project::new();
    p.write(
        "scene.toml",
        &LABELS.replace("name = \"labels\"", "name = \"scene\""),
    );
    p.run("scene.toml", &["--until", "scene"]).ok();
    p.write("labels.obj", &p.read("out/scene/scene/labels.obj"));
    let src = p.path("out/scene/scene/views");
    let set = cameras::read_views(&src).unwrap();
    let all: Vec<_> = set.train.iter().chain(&set.test).cloned().collect();
    assert_eq!(all.len(), 9);

    let cap = p.path("cap/views");
    let mut model = colmap::ColmapModel::default();
    for (i, cam) in all.iter().enumerate() {
        let v = cameras::read_view(&src, cam).unwrap();
        let name = format!("{i:04}.jpg");
        let mask = v.mask.expect("the synthetic views have masks");
        // A photo's own background (a light wall), not the renderer's black.
        let mut photo = v.rgb.clone();
        for (px, m) in photo.data.chunks_exact_mut(3).zip(&mask.data) {
            for (c, wall) in px.iter_mut().zip([0.75, 0.7, 0.6]) {
                *c = *c * m + wall * (1.0 - m);
            }
        }
        write_jpeg(&cap.join("images").join(&name), &photo);
        images::write_png(cap.join("masks").join(format!("{i:04}.png")), &mask).unwrap();
        let cid = model.cameras.len() as u32 + 1;
        model.cameras.push(colmap::ColmapCamera {
            id: cid,
            model: "PINHOLE".into(),
            width: cam.width as u64,
            height: cam.height as u64,
            params: vec![cam.fx as f64, cam.fy as f64, cam.cx as f64, cam.cy as f64],
        });
        let (q, t) = colmap::colmap_from_c2w(&cam.c2w);
        model.images.push(colmap::ColmapImage {
            id: i as u32 + 1,
            q,
            t,
            camera_id: cid,
            name,
        });
    }
    colmap::write_model_txt(&cap.join("sparse/0"), &model).unwrap();
    let read = cameras::read_views(&cap).unwrap();
    // 9 images: 0000 and 0008 held out.
    assert_eq!(
        read.test
            .iter()
            .map(|c| c.file_path.as_str())
            .collect::<Vec<_>>(),
        ["images/0000.jpg", "images/0008.jpg"]
    );
    assert_eq!(read.train.len(), 7);

    // The same 7 training cameras as a transforms.json directory with `_mask.png` files.
    let ngp = p.path("ngp");
    for cam in &read.train {
        let v = cameras::read_view(&cap, cam).unwrap();
        assert!(v.mask.is_some(), "masks/ is read");
        write_jpeg(&cameras::image_path(&ngp, cam), &v.rgb);
        images::write_png(cameras::mask_path(&ngp, cam), &v.mask.unwrap()).unwrap();
    }
    cameras::write_views(
        &ngp,
        &fure_stages::data::camera::CameraSet {
            train: read.train.clone(),
            test: vec![],
        },
    )
    .unwrap();

    hull(&p, "from_colmap", "cap/views").ok();
    hull(&p, "from_ngp", "ngp").ok();
    let m = |name: &str| read_json(&p.path(&format!("out/{name}/outer/metrics.json")));
    let (a, b) = (m("from_colmap"), m("from_ngp"));
    for key in ["volume", "area", "diagonal"] {
        let (x, y) = (a[key].as_f64().unwrap(), b[key].as_f64().unwrap());
        assert!(
            x > 0.0 && (x - y).abs() <= 0.01 * y,
            "{key}: COLMAP {x} vs transforms.json {y}"
        );
    }
    let parts =
        |name: &str| read_json(&p.path(&format!("out/{name}/parts/metrics.json")))["parts"].clone();
    assert_eq!(parts("from_colmap"), parts("from_ngp"));

    // The whole method on the JPEG capture, as a user runs it.
    let gt = read_json(&p.path("out/scene/scene/scene.json"));
    p.write(
        "cap/scene.json",
        &crate::method::capture_scene(&gt, 1.0, None),
    );
    p.write("cap/labels.obj", &p.read("out/scene/scene/labels.obj"));
    let shipped = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/capture.toml"),
    )
    .unwrap();
    p.write("cap/capture.toml", &shipped);
    let r = p.run("cap/capture.toml", &crate::method::TINY_CAPTURE);
    r.ok();
    assert_eq!(r.with("failed"), Vec::<&str>::new());
    let codec = read_json(&p.path("out/capture/codec/metrics.json"));
    assert_eq!(codec["method"], "codec", "{codec}");
    let fitted = codec["colors_fitted"][0].as_f64().unwrap();
    assert!(
        fitted > 0.5,
        "the JPEG photos coloured the strands: {codec}"
    );
    // The learner compares its renders with the photos over black (through the masks), so
    // the wall is no loss that no strand could remove (0.11 here; 0.63 when the wall counted).
    let rgb_loss = codec["final_losses"]["rgb"].as_f64().unwrap();
    assert!(
        rgb_loss < 0.3,
        "the photos' background reached the colour loss: {codec}"
    );
    // The tiny capture is already below the working size: its photos pass through.
    let resized = read_json(&p.path("out/capture/working_views/metrics.json"));
    assert_eq!(resized["factor"], 1, "{resized}");
    let maps = read_json(&p.path("out/capture/orientation/maps/index.json"));
    assert_eq!(maps["maps"].as_array().unwrap().len(), 7, "{maps}");

    // Without masks/ the RGB photos have nothing to carve with: the error names an image and
    // where its mask was looked for.
    std::fs::rename(cap.join("masks"), p.path("masks_aside")).unwrap();
    let r = hull(&p, "no_masks", "cap/views");
    assert_eq!(r.status("outer"), "failed", "{:?}", r.stages);
    let text = format!("{}{}", r.stdout(), r.stderr());
    eprintln!("{text}");
    // The first training view (0000 is held out).
    assert!(
        text.contains("cap/views/images/0001.jpg")
            && text.contains("masks/0001.png")
            && text.contains("images/0001_mask.png"),
        "the image and its mask files are not named:\n{text}"
    );
    assert!(text.contains("no alpha channel and no mask"), "{text}");
}

/// A capture made by other software: Debian's Blender grows its own particle hair on the tiny
/// tiger's labelled skin, renders it with Cycles (Principled Hair BSDF, Filmic, its own camera
/// convention) and writes the hair it rendered (`stages/src/scenes/synthetic/fur_capture.py`). The
/// shipped `capture.toml`, with an `evaluate` stage added on the GT ports, runs on it end to end;
/// the metric scale comes from the eyes and the strands land on Blender's hair (signed F at 4 cm
/// was 86.6 when written; a camera convention read wrongly scores near zero). Skipped with a
/// note without a `blender` on the PATH or with FURE_SKIP_BLENDER set, as the groom's check.
/// The synthetic views as photos taken through a barrel lens, calibrated by COLMAP's default
/// model (`SIMPLE_RADIAL`): every stage but `working_views` refuses the capture and says to read
/// it through that stage; through it, the visual hull is the pinhole capture's (0.5 % apart
/// when written), and the same photos taken for a pinhole's (the lens ignored) give another
/// (4.2 % smaller).
#[test]
fn a_capture_through_a_distorting_lens_reads_as_the_pinhole_capture() {
    use fure_stages::data::image::ImageF32;
    use fure_stages::formats::{cameras, colmap, images};
    let p = Project::new();
    p.write(
        "scene.toml",
        &LABELS.replace("name = \"labels\"", "name = \"scene\""),
    );
    p.run(
        "scene.toml",
        &["--until", "scene", "--set", "scene.resolution=128"],
    )
    .ok();
    p.write("labels.obj", &p.read("out/scene/scene/labels.obj"));
    let src = p.path("out/scene/scene/views");
    let set = cameras::read_views(&src).unwrap();
    let all: Vec<_> = set.train.iter().chain(&set.test).cloned().collect();

    // COLMAP's SIMPLE_RADIAL: x_d = x (1 + k r^2). Each photo pixel shows the pinhole's point
    // at radius r with r (1 + k r^2) = r_d (Newton), so the photo is the pinhole view resampled.
    let k = -0.5f64;
    let lens_photo = |im: &ImageF32, cam: &fure_stages::data::camera::Camera| {
        let mut out = ImageF32::new(im.width, im.height, im.channels);
        for v in 0..im.height {
            for u in 0..im.width {
                let xd = (u as f64 + 0.5 - cam.cx as f64) / cam.fx as f64;
                let yd = (v as f64 + 0.5 - cam.cy as f64) / cam.fy as f64;
                let rd = (xd * xd + yd * yd).sqrt();
                let mut r = rd;
                for _ in 0..30 {
                    r -= (r + k * r * r * r - rd) / (1.0 + 3.0 * k * r * r);
                }
                let s = if rd > 0.0 { r / rd } else { 1.0 };
                let (x, y) = (
                    cam.fx as f64 * xd * s + cam.cx as f64,
                    cam.fy as f64 * yd * s + cam.cy as f64,
                );
                im.sample_lanczos3(x, y, out.pixel_mut(u, v));
            }
        }
        out
    };
    let write_capture = |dir: &str, model_name: &str, through_lens: bool| {
        let photo = |im: &ImageF32, cam| {
            if through_lens {
                lens_photo(im, cam)
            } else {
                im.clone()
            }
        };
        let cap = p.path(dir);
        let mut model = colmap::ColmapModel::default();
        for (i, cam) in all.iter().enumerate() {
            let v = cameras::read_view(&src, cam).unwrap();
            let name = format!("{i:04}.png");
            images::write_png(cap.join("images").join(&name), &photo(&v.rgb, cam)).unwrap();
            let mask = photo(&v.mask.unwrap(), cam);
            images::write_png(cap.join("masks").join(&name), &mask).unwrap();
            let mut params = vec![cam.fx as f64, cam.cx as f64, cam.cy as f64];
            if model_name == "SIMPLE_RADIAL" {
                params.push(k);
            }
            model.cameras.push(colmap::ColmapCamera {
                id: i as u32 + 1,
                model: model_name.into(),
                width: cam.width as u64,
                height: cam.height as u64,
                params,
            });
            let (q, t) = colmap::colmap_from_c2w(&cam.c2w);
            model.images.push(colmap::ColmapImage {
                id: i as u32 + 1,
                q,
                t,
                camera_id: i as u32 + 1,
                name,
            });
        }
        colmap::write_model_bin(&cap.join("sparse/0"), &model).unwrap();
    };
    write_capture("lens/views", "SIMPLE_RADIAL", true);
    write_capture("ignored/views", "SIMPLE_PINHOLE", true);
    // The reference: the pinhole photos, the same split (every 8th image held out).
    write_capture("pinhole/views", "SIMPLE_PINHOLE", false);

    // Read directly, the capture is refused, naming the camera and the stage to read it through.
    let r = hull(&p, "direct", "lens/views");
    assert_eq!(r.status("outer"), "failed", "{:?}", r.stages);
    let text = format!("{}{}", r.stdout(), r.stderr());
    assert!(
        text.contains("SIMPLE_RADIAL") && text.contains("working_views"),
        "{text}"
    );

    p.write(
        "undistorted.toml",
        &HULL
            .replace("NAME", "undistorted")
            .replace("VIEWS", "working_views.views")
            .replace(
                "[stages.outer]",
                "[stages.working_views]\nkind = \"working_views\"\ninputs = { views = \"lens/views\" }\n\n[stages.outer]",
            ),
    );
    p.run("undistorted.toml", &[]).ok();
    let working = read_json(&p.path("out/undistorted/working_views/metrics.json"));
    assert_eq!(working["undistorted_views"], 9, "{working}");
    hull(&p, "pinhole", "pinhole/views").ok();
    hull(&p, "ignored", "ignored/views").ok();
    let volume = |name: &str| {
        read_json(&p.path(&format!("out/{name}/outer/metrics.json")))["volume"]
            .as_f64()
            .unwrap()
    };
    let (pinhole, undistorted, ignored) =
        (volume("pinhole"), volume("undistorted"), volume("ignored"));
    eprintln!("hull volume: pinhole {pinhole}, undistorted {undistorted}, lens ignored {ignored}");

    assert!(
        (undistorted / pinhole - 1.0).abs() < 0.01,
        "undistorted {undistorted} against the pinhole's {pinhole}"
    );
    assert!(
        (ignored / pinhole - 1.0).abs() > 0.03,
        "the control: the lens ignored gives {ignored} against {pinhole}"
    );
    // Every part transfers onto the undistorted hull (vertex counts differ with the mesh).
    let parts = |name: &str| {
        let m = read_json(&p.path(&format!("out/{name}/parts/metrics.json")));
        m["parts"]
            .as_object()
            .unwrap()
            .keys()
            .cloned()
            .collect::<Vec<_>>()
    };
    assert_eq!(parts("undistorted"), parts("pinhole"));
}

#[test]
fn a_capture_rendered_by_blender_runs_end_to_end() {
    let p = Project::new();
    p.write("tiny.toml", &crate::method::tiny_pipeline());
    p.run("tiny.toml", &["--until", "scene"]).ok();
    let scene = read_json(&p.path("out/tiny/scene/scene.json"));
    let s_cm = scene["s_cm"].as_f64().unwrap();
    let script =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("stages/src/scenes/synthetic/fur_capture.py");
    let length = format!("{}", 3.3 / s_cm);
    let mut cmd = std::process::Command::new("blender");
    cmd.args(["-b", "--factory-startup", "--python"])
        .arg(&script)
        .arg("--")
        .arg(p.path("out/tiny/scene/skin.obj"))
        .arg(p.path("cap"))
        .args(["--views", "16", "--test-views", "1", "--resolution", "96"])
        .args(["--hairs", "6000", "--samples", "8", "--length", &length]);
    let Some(run) = crate::groom::blender(cmd, "the Blender-rendered capture") else {
        return;
    };
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success() && stdout.contains(", 6000 strands"),
        "Blender did not render the capture ({}):\n{stdout}\n{}",
        run.status,
        String::from_utf8_lossy(&run.stderr)
    );

    // The user's side: eyes and part flags, no scale; the GT side only reaches `evaluate`.
    p.write(
        "cap/scene.json",
        &crate::method::capture_scene(&scene, 1.0, None),
    );
    p.write(
        "cap/gt/scene.json",
        &crate::method::capture_scene(&scene, 1.0, Some(s_cm)),
    );
    p.write("cap/labels.obj", &p.read("out/tiny/scene/skin.obj"));
    let shipped = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/capture.toml"),
    )
    .unwrap();
    p.write(
        "cap/capture.toml",
        &format!(
            "{shipped}\n[stages.evaluate]\nkind = \"evaluate\"\ninputs = {{ strands = \"codec.strands\", \
             gt_strands = \"gt/strands.hair\", gt_scene = \"gt/scene.json\", gt_skin = \"labels.obj\" }}\n"
        ),
    );
    let r = p.run("cap/capture.toml", &crate::method::TINY_CAPTURE);
    r.ok();
    assert_eq!(r.with("failed"), Vec::<&str>::new());

    let out = p.path("out/capture");
    let lengths = read_json(&out.join("lengths/metrics.json"));
    let recovered = lengths["s_cm"].as_f64().unwrap();
    assert!(
        (recovered - s_cm).abs() < 0.01 * s_cm,
        "s_cm {recovered} from the eyes, truth {s_cm}"
    );
    let eval = read_json(&out.join("evaluate/metrics.json"));
    let f4 = eval["prf_signed"]["4cm_40deg"]["fscore"].as_f64().unwrap();
    eprintln!("Blender-rendered capture: signed F {}", eval["prf_signed"]);
    assert!(
        f4 > 60.0,
        "signed F at 4 cm {f4}: the strands miss Blender's hair"
    );
}

/// Kind `blender_scene`: the tiny tiger's body with Blender's own hair, rendered by Cycles, in
/// place of `synthetic_scene` in `tiger.toml` (tiny sizes), end to end. The hair Blender
/// rendered is the ground truth: its parts come from the skin's labels (bare parts get no
/// statistics), the same body regrown with another Blender seed scores high against it (the
/// ceiling; 3 cm signed F 95.4 when written: at 64 px the hair is sparse), and the codec's
/// strands land on it (4 cm signed F 70.8 when written). About 7 s; skipped with a note
/// without Blender, as the capture above.
#[test]
fn a_scene_blender_grew_and_rendered_runs_through_the_pipeline() {
    let mut version = std::process::Command::new("blender");
    version.arg("--version");
    if crate::groom::blender(version, "the Blender-rendered scene").is_none() {
        return;
    }
    let p = Project::new();
    p.write("tiny.toml", &crate::method::tiny_pipeline());
    p.write(
        "bl.toml",
        "extends = \"tiny.toml\"\n[pipeline]\nname = \"bl\"\n\n[stages.scene]\nkind = \"blender_scene\"\n\n\
         [stages.ceiling]\nkind = \"evaluate\"\ninputs = { strands = \"scene.regrown\", gt_strands = \"scene.strands\", \
         gt_scene = \"scene.scene\", gt_skin = \"scene.skin\" }\n",
    );
    let r = p.run("bl.toml", &[]);
    r.ok();
    assert_eq!(r.with("failed"), Vec::<&str>::new());

    let out = p.path("out/bl");
    let report = read_json(&out.join("scene/report.json"));
    assert_eq!(report["renderer"], "blender");
    assert!(report["strands"].as_u64().unwrap() > 100, "{report}");
    let scene = read_json(&out.join("scene/scene.json"));
    for (part, info) in scene["parts"].as_object().unwrap() {
        let len = info["mean_length_cm"].as_f64().unwrap();
        if info["fur"].as_bool().unwrap() {
            assert!(len > 0.5, "fur part {part}: mean length {len} cm");
        } else {
            assert_eq!(len, 0.0, "bare part {part}");
        }
    }
    let fscore = |stage: &str, t: &str| {
        read_json(&out.join(stage).join("metrics.json"))["prf_signed"][t]["fscore"]
            .as_f64()
            .unwrap()
    };
    let ceiling = fscore("ceiling", "3cm_30deg");
    let codec = fscore("evaluate", "4cm_40deg");
    eprintln!("Blender scene: ceiling F 3 cm {ceiling:.1}, codec F 4 cm {codec:.1}");
    assert!(
        ceiling > 90.0,
        "the regrown Blender hair scores {ceiling} at 3 cm"
    );
    assert!(
        codec > 50.0,
        "the codec's strands miss Blender's hair: F 4 cm {codec}"
    );
}
