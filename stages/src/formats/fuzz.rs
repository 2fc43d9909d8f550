//! Property-based fuzzing of every reader (proptest; no nightly toolchain, so no `cargo fuzz`).
//!
//! Each target feeds a reader two kinds of input, through a real file as the stages do:
//!
//! - arbitrary bytes (and, for text formats, arbitrary text made of the format's own tokens), and
//! - mutations of a valid file written by our own writer: byte flips and overwrites, insertions
//!   of "interesting" tokens (`nan`, `inf`, `-1`, `0`, `4294967296`, `1e40`, ...), deletions,
//!   duplicated ranges and truncation.
//!
//! The property is the formats contract: the reader never panics (proptest turns a panic into a
//! failing, shrunk case) and, when it fails, returns a [`FormatError`] naming the file it was
//! given; every value it returns is finite. Readers must also not allocate from a size a header
//! merely claims (a 4-billion-strand `.hair` header is 128 bytes long), or a case would abort the
//! process instead of failing: the targets run in the test process, so that shows up as a crash.
//!
//! By default each target runs [`DEFAULT_CASES`] cases so CI stays fast; set `PROPTEST_CASES` for
//! a long run, e.g. `PROPTEST_CASES=200000 cargo test --release -p fure-stages --lib fuzz_obj`.
//! Failures are not persisted to files: every panic found becomes a named regression test (see
//! the `regression_` tests at the end of this file and in the readers' own modules).

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3};
use proptest::prelude::*;
use proptest::test_runner::Config;

use super::FormatError;
use crate::data::camera::{Camera, CameraSet};
use crate::data::image::ImageF32;
use crate::data::mesh::Mesh;
use crate::data::strands::Strands;

/// Cases per target when `PROPTEST_CASES` is not set.
pub const DEFAULT_CASES: u32 = 64;

fn config() -> Config {
    let cases = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(DEFAULT_CASES);
    Config {
        cases,
        failure_persistence: None,
        // The short default run (CI) is reproducible: a fixed seed unless a long run
        // (`PROPTEST_CASES`) or `PROPTEST_RNG_SEED` asks for other inputs.
        rng_seed: ci_seed(),
        // Shrinking a byte vector is cheap; keep the default iteration budget.
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

/// Tokens that break number parsers and size checks.
const INTERESTING: &[&str] = &[
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e40",
    "-1e40",
    "-1",
    "0",
    "-0",
    "4294967295",
    "4294967296",
    "18446744073709551616",
    "-9223372036854775808",
    "1.5",
    "//",
    "/",
    " ",
    "\n",
    "\0",
    "\u{feff}",
    "é",
    "#",
    "{",
    "}",
    "[",
    "]",
    "\"",
    ",",
    ":",
    "null",
    "true",
];

/// One edit of a byte buffer; positions are taken modulo the buffer length.
#[derive(Debug, Clone)]
enum Mutation {
    Flip(usize, u8),
    Set(usize, u8),
    Insert(usize, Vec<u8>),
    Token(usize, usize),
    Delete(usize, usize),
    Duplicate(usize, usize, usize),
    Truncate(usize),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), 1u8..=255).prop_map(|(p, b)| Mutation::Flip(p, b)),
        (any::<usize>(), any::<u8>()).prop_map(|(p, b)| Mutation::Set(p, b)),
        (any::<usize>(), proptest::collection::vec(any::<u8>(), 1..8))
            .prop_map(|(p, b)| Mutation::Insert(p, b)),
        (any::<usize>(), 0..INTERESTING.len()).prop_map(|(p, t)| Mutation::Token(p, t)),
        (any::<usize>(), 1usize..64).prop_map(|(p, n)| Mutation::Delete(p, n)),
        (any::<usize>(), 1usize..64, any::<usize>())
            .prop_map(|(a, n, b)| Mutation::Duplicate(a, n, b)),
        any::<usize>().prop_map(Mutation::Truncate),
    ]
}

fn mutations() -> impl Strategy<Value = Vec<Mutation>> {
    proptest::collection::vec(mutation(), 1..6)
}

fn apply(mut b: Vec<u8>, muts: &[Mutation]) -> Vec<u8> {
    for m in muts {
        let len = b.len();
        let at = |p: usize| if len == 0 { 0 } else { p % (len + 1) };
        match m {
            Mutation::Flip(p, x) if len > 0 => b[p % len] ^= x,
            Mutation::Set(p, x) if len > 0 => b[p % len] = *x,
            Mutation::Insert(p, bytes) => {
                let i = at(*p);
                b.splice(i..i, bytes.iter().copied());
            }
            Mutation::Token(p, t) => {
                // Replace the token (run of non-space bytes) around p, or insert at the end.
                let i = at(*p);
                let start = b[..i]
                    .iter()
                    .rposition(|c| c.is_ascii_whitespace())
                    .map_or(0, |k| k + 1);
                let end = b[i..]
                    .iter()
                    .position(|c| c.is_ascii_whitespace())
                    .map_or(len, |k| i + k);
                b.splice(start..end, INTERESTING[*t].bytes());
            }
            Mutation::Delete(p, n) if len > 0 => {
                let i = p % len;
                b.drain(i..(i + n).min(len));
            }
            Mutation::Duplicate(a, n, dst) if len > 0 => {
                let i = a % len;
                let piece: Vec<u8> = b[i..(i + n).min(len)].to_vec();
                let d = at(*dst);
                b.splice(d..d, piece);
            }
            Mutation::Truncate(p) => b.truncate(at(*p)),
            _ => {}
        }
    }
    b
}

/// A scratch directory per test thread, reused across cases.
fn scratch() -> tempfile::TempDir {
    tempfile::tempdir().expect("temp dir")
}

/// The contract on a reader's result for the file at `path`.
fn check<T>(
    path: &Path,
    r: Result<T, FormatError>,
    finite: impl Fn(&T) -> bool,
) -> Result<(), TestCaseError> {
    match r {
        Ok(v) => {
            prop_assert!(finite(&v), "reader returned non-finite values");
            Ok(())
        }
        Err(e) => {
            let msg = e.to_string();
            prop_assert!(
                e.path() == path || e.path().starts_with(path.parent().unwrap_or(path)),
                "error names {} instead of {}: {msg}",
                e.path().display(),
                path.display()
            );
            prop_assert!(
                msg.contains(&*path.file_name().unwrap_or_default().to_string_lossy())
                    || msg.contains(&*path.parent().unwrap_or(path).to_string_lossy()),
                "message does not name the file: {msg}"
            );
            Ok(())
        }
    }
}

fn write(path: &Path, bytes: &[u8]) {
    std::fs::write(path, bytes).expect("write scratch file");
}

// ---- valid seeds, written by our own writers ----

fn seed_mesh() -> Mesh {
    // A labelled tetrahedron plus a quad.
    let positions = vec![
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(2.0, 2.0, 2.0),
    ];
    let mut m = Mesh {
        positions,
        triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [1, 4, 2]],
        part: vec![0, 0, 1, 1, 1],
        part_names: vec!["torso".into(), "head".into()],
        ..Default::default()
    };
    m.recompute_normals();
    m
}

fn seed_strands() -> Strands {
    let mut s = Strands::new();
    s.push(
        &[
            Vec3::ZERO,
            Vec3::new(0.0, 0.1, 0.0),
            Vec3::new(0.0, 0.2, 0.05),
        ],
        0,
        0.01,
        [0.8, 0.4, 0.1],
    );
    s.push(
        &[Vec3::X, Vec3::new(1.0, 0.1, 0.0)],
        1,
        0.02,
        [0.1, 0.1, 0.1],
    );
    s.part_names = vec!["torso".into(), "tail".into()];
    s
}

fn seed_image(channels: u32) -> ImageF32 {
    let mut im = ImageF32::new(7, 5, channels);
    for (i, v) in im.data.iter_mut().enumerate() {
        *v = ((i * 37) % 101) as f32 / 100.0;
    }
    im
}

fn seed_cameras() -> CameraSet {
    let cam = |i: usize| Camera {
        file_path: format!("train/{i:03}.png"),
        c2w: Mat4::from_translation(Vec3::new(i as f32, 0.0, 4.0)),
        fx: 50.0,
        fy: 50.0 + i as f32,
        cx: 16.0,
        cy: 12.0,
        width: 32,
        height: 24,
    };
    CameraSet {
        train: vec![cam(0), cam(1)],
        test: vec![cam(2)],
    }
}

fn seed_bytes(dir: &Path, name: &str, write: impl FnOnce(&Path)) -> Vec<u8> {
    let p = dir.join(format!("seed-{name}"));
    write(&p);
    std::fs::read(p).expect("seed written")
}

fn mesh_finite(m: &Mesh) -> bool {
    m.positions.iter().chain(&m.normals).all(|p| p.is_finite())
}

fn strands_finite(s: &Strands) -> bool {
    s.points.iter().all(|p| p.is_finite())
        && s.width.iter().all(|w| w.is_finite())
        && s.color.iter().flatten().all(|c| c.is_finite())
}

fn image_finite(_: &ImageF32) -> bool {
    // EXR may legitimately hold non-finite pixels; the stages that read images check them.
    true
}

fn cameras_finite(c: &[Camera]) -> bool {
    c.iter().all(|c| {
        c.c2w.is_finite()
            && [c.fx, c.fy, c.cx, c.cy].iter().all(|v| v.is_finite())
            && c.width > 0
            && c.height > 0
    })
}

fn views_finite(c: &CameraSet) -> bool {
    cameras_finite(&c.train) && cameras_finite(&c.test)
}

/// Arbitrary text built from a format's vocabulary (so the parser gets past its first token).
/// Tokens of COLMAP's text model files.
const COLMAP_WORDS: &[&str] = &[
    "\n",
    "\n",
    "\n",
    " ",
    " ",
    " ",
    "#",
    "PINHOLE",
    "SIMPLE_PINHOLE",
    "SIMPLE_RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "1",
    "2",
    "0.5",
    "-0.5",
    "a.png",
    "images/b.jpg",
];

fn vocabulary_text(words: &'static [&'static str]) -> impl Strategy<Value = Vec<u8>> {
    proptest::collection::vec(
        prop_oneof![
            (0..words.len()).prop_map(move |i| words[i].to_string()),
            (0..INTERESTING.len()).prop_map(|i| INTERESTING[i].to_string()),
            (-5i64..70000).prop_map(|i| i.to_string()),
            any::<f32>().prop_map(|f| f.to_string()),
        ],
        0..80,
    )
    .prop_map(|toks| {
        let mut out = String::new();
        for (i, t) in toks.iter().enumerate() {
            out.push_str(t);
            out.push(if i % 5 == 4 { '\n' } else { ' ' });
        }
        out.into_bytes()
    })
}

const OBJ_WORDS: &[&str] = &[
    "v",
    "vn",
    "vt",
    "f",
    "g",
    "o",
    "l",
    "s",
    "usemtl",
    "1//1",
    "2/2/2",
    "-1",
    "3/",
    "# fure-vertex-parts",
    "\n",
];

const PLY_WORDS: &[&str] = &[
    "ply",
    "format ascii 1.0",
    "format binary_little_endian 1.0",
    "format binary_big_endian 1.0",
    "element vertex",
    "element edge",
    "property float x",
    "property float y",
    "property float z",
    "property int vertex1",
    "property int vertex2",
    "property list uchar int vertex_indices",
    "property ushort part",
    "comment fure parts [\"a\"]",
    "end_header",
    "\n",
];

const JSON_WORDS: &[&str] = &[
    "{",
    "}",
    "[",
    "]",
    ",",
    ":",
    "\"frames\"",
    "\"file_path\"",
    "\"transform_matrix\"",
    "\"fl_x\"",
    "\"w\"",
    "\"h\"",
    "\"camera_angle_x\"",
    "\"intrinsic_matrix\"",
    "\"values\"",
    "\"train/000.png\"",
];

fn run_obj(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("m.obj");
    write(&p, bytes);
    check(&p, super::obj::read_obj(&p), mesh_finite)
}

fn run_ply(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("s.ply");
    write(&p, bytes);
    check(&p, super::ply::read_ply_strands(&p), strands_finite)?;
    check(
        &p,
        super::ply::read_ply_points_as_strands(&p, 3),
        strands_finite,
    )
}

fn run_hair(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("s.hair");
    write(&p, bytes);
    check(&p, super::hair::read_hair(&p), strands_finite)
}

fn run_scalars(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("v.json");
    write(&p, bytes);
    check(&p, super::scalars::read_scalars(&p), |v: &Vec<f32>| {
        v.iter().all(|x| x.is_finite())
    })
}

fn run_transforms(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("transforms.json");
    write(&p, bytes);
    check(
        &p,
        super::cameras::read_transforms(&p),
        |c: &Vec<Camera>| cameras_finite(c),
    )?;
    check(&p, super::cameras::read_views(dir), views_finite)
}

/// A COLMAP model with one of its files (`cameras.txt`, `images.bin`, ...) replaced by `bytes`
/// and the other file of the same format valid.
fn run_colmap(dir: &Path, file: &str, bytes: &[u8]) -> Result<(), TestCaseError> {
    let ext = if file.ends_with(".bin") { "bin" } else { "txt" };
    let sparse = dir.join(format!("colmap_{ext}"));
    std::fs::create_dir_all(&sparse).expect("scratch dir");
    for other in ["cameras", "images"] {
        let name = format!("{other}.{ext}");
        let content = if name == file {
            bytes.to_vec()
        } else {
            seeds().colmap[&name].clone()
        };
        write(&sparse.join(&name), &content);
    }
    let p = sparse.join(file);
    check(&p, super::colmap::read_model(&sparse), |m| {
        m.cameras
            .iter()
            .all(|c| c.params.iter().all(|v| v.is_finite()))
            && m.images
                .iter()
                .all(|i| i.q.iter().chain(&i.t).all(|v| v.is_finite()))
    })?;
    let model = super::colmap::read_model(&sparse);
    if let Ok(model) = model {
        let r = super::colmap::model_cameras(&model, &sparse.join(format!("cameras.{ext}")), &p);
        check(&p, r, |c: &Vec<Camera>| cameras_finite(c))?;
    }
    Ok(())
}

fn run_png(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("i.png");
    write(&p, bytes);
    check(&p, super::images::read_png(&p), image_finite)?;
    check(&p, super::images::image_size(&p), |_| true)
}

fn run_exr(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("i.exr");
    write(&p, bytes);
    check(&p, super::images::read_exr(&p), image_finite)?;
    check(&p, super::images::image_size(&p), |_| true)
}

fn run_jpeg(dir: &Path, bytes: &[u8]) -> Result<(), TestCaseError> {
    let p = dir.join("i.jpg");
    write(&p, bytes);
    check(&p, super::images::read_image(&p), image_finite)?;
    check(&p, super::images::image_size(&p), |_| true)
}

/// Valid seed files, written once per test.
struct Seeds {
    _dir: tempfile::TempDir,
    obj: Vec<u8>,
    ply_bin: Vec<u8>,
    ply_ascii: Vec<u8>,
    hair: Vec<u8>,
    scalars: Vec<u8>,
    transforms: Vec<u8>,
    png8: Vec<u8>,
    png_gray: Vec<u8>,
    exr: Vec<u8>,
    /// `cameras.txt`, `images.txt`, `cameras.bin`, `images.bin` of a small COLMAP model.
    colmap: std::collections::BTreeMap<String, Vec<u8>>,
}

impl Seeds {
    fn new() -> Seeds {
        let dir = scratch();
        let d = dir.path().to_path_buf();
        let obj = seed_bytes(&d, "m.obj", |p| {
            super::obj::write_obj(p, &seed_mesh()).unwrap()
        });
        let ply_bin = seed_bytes(&d, "s.ply", |p| {
            super::ply::write_ply_strands(p, &seed_strands()).unwrap()
        });
        let ply_ascii = seed_bytes(&d, "a.ply", |p| {
            super::ply::write_ply_strands_ascii(p, &seed_strands()).unwrap()
        });
        let hair = seed_bytes(&d, "s.hair", |p| {
            super::hair::write_hair(p, &seed_strands()).unwrap()
        });
        let scalars = seed_bytes(&d, "v.json", |p| {
            super::scalars::write_scalars(p, &[0.5, -1.0, 3.25]).unwrap()
        });
        let transforms = {
            let vd = d.join("views");
            super::cameras::write_views(&vd, &seed_cameras()).unwrap();
            std::fs::read(vd.join("transforms.json")).unwrap()
        };
        let png8 = seed_bytes(&d, "i.png", |p| {
            super::images::write_png(p, &seed_image(4)).unwrap()
        });
        let png_gray = seed_bytes(&d, "g.png", |p| {
            super::images::write_png(p, &seed_image(1)).unwrap()
        });
        let exr = seed_bytes(&d, "i.exr", |p| {
            super::images::write_exr(p, &seed_image(3)).unwrap()
        });
        let colmap = {
            let cd = d.join("colmap");
            let mut model = super::colmap::ColmapModel::default();
            model.cameras.push(super::colmap::ColmapCamera {
                id: 1,
                model: "PINHOLE".into(),
                width: 8,
                height: 6,
                params: vec![7.5, 7.25, 4.0, 3.0],
            });
            model.cameras.push(super::colmap::ColmapCamera {
                id: 2,
                model: "SIMPLE_RADIAL".into(),
                width: 8,
                height: 6,
                params: vec![7.5, 4.0, 3.0, 0.0],
            });
            for (i, c) in seed_cameras().train.iter().enumerate() {
                let (q, t) = super::colmap::colmap_from_c2w(&c.c2w);
                model.images.push(super::colmap::ColmapImage {
                    id: i as u32 + 1,
                    q,
                    t,
                    camera_id: 1 + i as u32 % 2,
                    name: format!("im {i}.png"),
                });
            }
            super::colmap::write_model_txt(&cd, &model).unwrap();
            super::colmap::write_model_bin(&cd, &model).unwrap();
            ["cameras.txt", "images.txt", "cameras.bin", "images.bin"]
                .iter()
                .map(|n| (n.to_string(), std::fs::read(cd.join(n)).unwrap()))
                .collect()
        };
        Seeds {
            _dir: dir,
            colmap,
            obj,
            ply_bin,
            ply_ascii,
            hair,
            scalars,
            transforms,
            png8,
            png_gray,
            exr,
        }
    }
}

fn seeds() -> &'static Seeds {
    static SEEDS: std::sync::OnceLock<Seeds> = std::sync::OnceLock::new();
    SEEDS.get_or_init(Seeds::new)
}

fn arbitrary_bytes() -> impl Strategy<Value = Vec<u8>> {
    proptest::collection::vec(any::<u8>(), 0..1024)
}

thread_local! {
    /// One scratch directory per test thread, reused by every case of the target
    /// running on that thread (creating a directory per case made the runs
    /// I/O-bound). Targets run on separate threads, so they never share files.
    static WORKDIR: tempfile::TempDir = scratch();
}

/// The scratch directory of this thread.
fn workdir() -> PathBuf {
    WORKDIR.with(|d| d.path().to_path_buf())
}

#[test]
fn seeds_read_back() {
    // The mutation targets start from valid files: make sure they are.
    let s = seeds();
    let dir = workdir();
    let p = dir.join("m.obj");
    write(&p, &s.obj);
    assert_eq!(super::obj::read_obj(&p).unwrap().triangles.len(), 5);
    let p = dir.join("s.ply");
    write(&p, &s.ply_ascii);
    assert_eq!(super::ply::read_ply_strands(&p).unwrap().len(), 2);
    write(&p, &s.ply_bin);
    assert_eq!(super::ply::read_ply_strands(&p).unwrap().len(), 2);
    let p = dir.join("s.hair");
    write(&p, &s.hair);
    assert_eq!(super::hair::read_hair(&p).unwrap().len(), 2);
    let p = dir.join("transforms.json");
    write(&p, &s.transforms);
    assert_eq!(super::cameras::read_transforms(&p).unwrap().len(), 2);
    let p = dir.join("i.png");
    write(&p, &s.png8);
    assert_eq!(super::images::read_png(&p).unwrap().channels, 4);
    write(&p, &s.png_gray);
    assert_eq!(super::images::read_png(&p).unwrap().channels, 1);
    let p = dir.join("i.exr");
    write(&p, &s.exr);
    assert_eq!(super::images::read_exr(&p).unwrap().width, 7);
    let p = dir.join("v.json");
    write(&p, &s.scalars);
    assert_eq!(super::scalars::read_scalars(&p).unwrap().len(), 3);
    for ext in ["txt", "bin"] {
        let d = dir.join(format!("seed_colmap_{ext}"));
        std::fs::create_dir_all(&d).unwrap();
        for f in ["cameras", "images"] {
            let name = format!("{f}.{ext}");
            write(&d.join(&name), &s.colmap[&name]);
        }
        let m = super::colmap::read_model(&d).unwrap();
        let c = super::colmap::model_cameras(&m, &d.join("cameras"), &d.join("images")).unwrap();
        assert_eq!(c.len(), 2);
    }
}

#[test]
fn mutation_changes_bytes() {
    // The harness itself: a truncation and a token replacement do what they say.
    let b = b"v 1 2 3\nf 1 2 3\n".to_vec();
    assert_eq!(apply(b.clone(), &[Mutation::Truncate(5)]), b"v 1 2");
    let t = apply(b, &[Mutation::Token(2, 0)]);
    assert_eq!(t, b"v nan 2 3\nf 1 2 3\n");
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn fuzz_obj_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        run_obj(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_obj_tokens(bytes in vocabulary_text(OBJ_WORDS)) {
        let dir = workdir();
        run_obj(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_obj_mutations(m in mutations()) {
        let dir = workdir();
        run_obj(&dir, &apply(seeds().obj.clone(), &m))?;
    }

    #[test]
    fn fuzz_ply_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        run_ply(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_ply_tokens(bytes in vocabulary_text(PLY_WORDS)) {
        let dir = workdir();
        run_ply(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_ply_mutations(m in mutations(), ascii in any::<bool>()) {
        let s = seeds();
        let seed = if ascii { &s.ply_ascii } else { &s.ply_bin };
        let dir = workdir();
        run_ply(&dir, &apply(seed.clone(), &m))?;
    }

    #[test]
    fn fuzz_hair_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        run_hair(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_hair_mutations(m in mutations()) {
        let dir = workdir();
        run_hair(&dir, &apply(seeds().hair.clone(), &m))?;
    }

    #[test]
    fn fuzz_scalars_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        run_scalars(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_scalars_mutations(m in mutations()) {
        let dir = workdir();
        run_scalars(&dir, &apply(seeds().scalars.clone(), &m))?;
    }

    #[test]
    fn fuzz_transforms_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        run_transforms(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_transforms_tokens(bytes in vocabulary_text(JSON_WORDS)) {
        let dir = workdir();
        run_transforms(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_transforms_mutations(m in mutations()) {
        let dir = workdir();
        run_transforms(&dir, &apply(seeds().transforms.clone(), &m))?;
    }

    #[test]
    fn fuzz_colmap_bytes(bytes in arbitrary_bytes(), k in 0..4usize) {
        let dir = workdir();
        run_colmap(&dir, ["cameras.txt", "images.txt", "cameras.bin", "images.bin"][k], &bytes)?;
    }

    #[test]
    fn fuzz_colmap_tokens(bytes in vocabulary_text(COLMAP_WORDS), images in any::<bool>()) {
        let dir = workdir();
        run_colmap(&dir, if images { "images.txt" } else { "cameras.txt" }, &bytes)?;
    }

    #[test]
    fn fuzz_colmap_mutations(m in mutations(), k in 0..4usize) {
        let dir = workdir();
        let file = ["cameras.txt", "images.txt", "cameras.bin", "images.bin"][k];
        run_colmap(&dir, file, &apply(seeds().colmap[file].clone(), &m))?;
    }

    #[test]
    fn fuzz_png_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        run_png(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_png_mutations(m in mutations(), gray in any::<bool>()) {
        let s = seeds();
        let seed = if gray { &s.png_gray } else { &s.png8 };
        let dir = workdir();
        run_png(&dir, &apply(seed.clone(), &m))?;
    }

    #[test]
    fn fuzz_exr_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        run_exr(&dir, &bytes)?;
    }

    #[test]
    fn fuzz_exr_mutations(m in mutations()) {
        let dir = workdir();
        run_exr(&dir, &apply(seeds().exr.clone(), &m))?;
    }

    #[test]
    fn fuzz_jpeg_bytes(bytes in arbitrary_bytes()) {
        let dir = workdir();
        // A JPEG start-of-image marker first, so the decoder gets past the magic.
        let mut b = vec![0xFF, 0xD8, 0xFF];
        b.extend_from_slice(&bytes);
        run_jpeg(&dir, &b)?;
    }
}
