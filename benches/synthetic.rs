//! Benchmark of the `synthetic_scene` stage: the default tiger (or `FURE_BENCH_PRESET`, `FURE_BENCH_SIZE`),
//! generated, rendered and written once. Prints strands, segments, rays per second and seconds.
//!
//!     cargo bench --bench synthetic

use std::collections::BTreeMap;
use std::time::Instant;

use fure_stage_api::{NoProgress, Params, StageContext};
use fure_stages::scenes::synthetic::{run_settings, Settings};

fn main() {
    let preset = std::env::var("FURE_BENCH_PRESET").unwrap_or_else(|_| "tiger".to_string());
    let size = std::env::var("FURE_BENCH_SIZE").unwrap_or_else(|_| "default".to_string());
    let st = Settings::new(&preset, &size);
    let dir = tempfile::tempdir().expect("temporary directory");
    let files = [
        ("views", "views"),
        ("skin", "skin.obj"),
        ("strands", "strands.hair"),
        ("strands_ply", "strands_ply.ply"),
        ("scene", "scene.json"),
        ("report", "report.json"),
    ];
    let outputs: BTreeMap<String, std::path::PathBuf> = files
        .iter()
        .map(|(p, f)| (p.to_string(), dir.path().join(f)))
        .collect();
    std::fs::create_dir_all(dir.path().join("views")).expect("views directory");
    let params = Params::default();
    let ctx = StageContext {
        name: "bench",
        params: &params,
        inputs: BTreeMap::new(),
        outputs,
        progress: &NoProgress,
    };
    let t0 = Instant::now();
    if let Err(e) = run_settings(&st, &ctx) {
        eprintln!("synthetic_scene failed: {e}");
        std::process::exit(1);
    }
    let total = t0.elapsed().as_secs_f64();
    let text = std::fs::read_to_string(dir.path().join("report.json")).expect("report.json");
    let r: serde_json::Value = serde_json::from_str(&text).expect("report.json is JSON");
    println!(
        "synthetic_scene {preset} ({size}): {} px x{} ss, {} + {} views, threads {}",
        r["resolution"],
        r["supersample"],
        r["views"],
        r["test_views"],
        rayon::current_num_threads()
    );
    println!("strands          {}", r["strands"]);
    println!("segments         {}", r["segments"]);
    println!("skin triangles   {}", r["skin"]["triangles"]);
    println!("rays             {}", r["rays"]);
    println!(
        "rays per second  {:.0}",
        r["seconds"]["rays_per_second"].as_f64().unwrap_or(0.0)
    );
    println!(
        "seconds          build {:.2}, render {:.2}, total {:.2}",
        r["seconds"]["build"].as_f64().unwrap_or(0.0),
        r["seconds"]["render"].as_f64().unwrap_or(0.0),
        total
    );
}
