//! Benchmark of the learners' own work per iteration (`cargo bench --bench learn`).
//!
//! At the synthetic tiger's sizes (52,542 strands of L = 8 points, 4,000 sampled per
//! iteration, 10 positional-encoding frequencies, 10 parts, a 64 x 3 encoder and 21 basis
//! components) it times one iteration of each model without the renderer: the codec's
//! forward (encoder, decoder, placement), backward and Adam step, and the dense baseline's
//! forward, backward and lazy Adam step on the same subsets, median of several iterations.
//! The dense model is the baseline measured in the same run: the printed ratio is what the
//! codec adds per iteration on top of the work both learners share (rendering and losses,
//! timed by `cargo bench --bench render` and, end to end, by
//! `fure run pipelines/speed_accuracy.toml`). Figures are also written as JSON to
//! `target/bench/learn.json`.
//!
//! Environment: `RAYON_NUM_THREADS` sets the thread count.

use std::time::Instant;

use fure_stages::growth::learn::mlp::{Mlp, PositionalEncoding};
use fure_stages::growth::learn::model::{Codec, Dense, Model, Prepared, Rates, RootInputs};
use fure_stages::growth::learn::placement::Decoder;
use fure_stages::growth::learn::train::subset;
use fure_stages::render::{Mat3, Vec3};

mod common;
use common::Rng;

const STRANDS: usize = 52_542;
const SAMPLED: usize = 4_000;
const POINTS: usize = 8;
const PARTS: usize = 10;
const COMPONENTS: usize = 21;
const REPS: usize = 15;

/// Roots on a unit sphere with identity frames, 4 cm strands.
fn prepared(rng: &mut Rng) -> Prepared {
    let roots: Vec<Vec3> = (0..STRANDS)
        .map(|_| {
            let z = 2.0 * rng.next() - 1.0;
            let phi = std::f32::consts::TAU * rng.next();
            let r = (1.0 - z * z).max(0.0).sqrt();
            Vec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect();
    let parts: Vec<u16> = (0..STRANDS).map(|i| (i % PARTS) as u16).collect();
    let rho: Vec<f32> = (0..STRANDS).map(|_| rng.next()).collect();
    let pe = PositionalEncoding::new(10, [-1.0; 3], [1.0; 3]);
    let inputs = RootInputs {
        positions: roots,
        frames: vec![Mat3::IDENTITY; STRANDS],
        lengths: vec![0.04; STRANDS],
        parts,
        rho,
    };
    Prepared::new(POINTS, inputs, PARTS, &pe)
}

/// A straight mean strand and small random components.
fn decoder(rng: &mut Rng) -> (Vec<Vec3>, Decoder) {
    let mean: Vec<Vec3> = (0..POINTS)
        .map(|i| Vec3::Z * i as f32 / (POINTS - 1) as f32)
        .collect();
    let comps: Vec<Vec<Vec3>> = (0..COMPONENTS)
        .map(|_| {
            (0..POINTS)
                .map(|_| 0.02 * Vec3::new(rng.next() - 0.5, rng.next() - 0.5, rng.next() - 0.5))
                .collect()
        })
        .collect();
    let dec = Decoder::new(&mean, &comps);
    (mean, dec)
}

/// Median seconds of one forward + backward + step, and the same split.
fn time_model(model: &mut Model, prep: &Prepared, rng: &mut Rng) -> [f64; 4] {
    let rates = Rates {
        encoder: 1e-3,
        decoder: 1e-5,
        points: 1e-3,
        length: 0.05,
        style: 0.05,
        style_codes: 0.3,
    };
    let mut runs: Vec<[f64; 4]> = Vec::new();
    for it in 0..REPS + 2 {
        let ids = subset(STRANDS, SAMPLED, 7, it);
        let t0 = Instant::now();
        let (points, cache) = model.forward(prep, &ids);
        let t1 = Instant::now();
        let grad: Vec<Vec3> = (0..points.len())
            .map(|_| 1e-3 * Vec3::new(rng.next() - 0.5, rng.next() - 0.5, rng.next() - 0.5))
            .collect();
        let t2 = Instant::now();
        let grads = model.backward(prep, &ids, &cache, &grad);
        let t3 = Instant::now();
        model.step(&grads, &ids, rates);
        let t4 = Instant::now();
        std::hint::black_box(points);
        let f = (t1 - t0).as_secs_f64();
        let b = (t3 - t2).as_secs_f64();
        let s = (t4 - t3).as_secs_f64();
        // The first two iterations warm the allocator and the thread pool.
        if it >= 2 {
            runs.push([f + b + s, f, b, s]);
        }
    }
    runs.sort_by(|a, b| a[0].total_cmp(&b[0]));
    runs[runs.len() / 2]
}

fn main() {
    let mut rng = Rng(1);
    let prep = prepared(&mut rng);
    let (mean, dec) = decoder(&mut rng);
    let mut mlp = Mlp::new(prep.feature_dim, 64, 3, COMPONENTS, 1);
    // A non-zero output layer, as after a few training steps (it starts at zero).
    let n = mlp.param_count();
    for w in &mut mlp.params[n - (64 + 1) * COMPONENTS..] {
        *w = 0.1 * (rng.next() - 0.5);
    }
    let mut codec = Model::Codec(Codec::new(mlp, dec, true, false));
    let mut dense = Model::Dense(Dense::from_local(&mean, STRANDS));

    let c = time_model(&mut codec, &prep, &mut rng);
    let d = time_model(&mut dense, &prep, &mut rng);
    let ms = |x: f64| x * 1e3;
    println!(
        "{SAMPLED} of {STRANDS} strands, L = {POINTS}, encoder {} -> 64 x 3 -> {COMPONENTS}, median of {REPS}",
        prep.feature_dim
    );
    println!(
        "codec: {:.2} ms per iteration (forward {:.2}, backward {:.2}, step {:.2})",
        ms(c[0]),
        ms(c[1]),
        ms(c[2]),
        ms(c[3])
    );
    println!(
        "dense: {:.2} ms per iteration (forward {:.2}, backward {:.2}, step {:.2})",
        ms(d[0]),
        ms(d[1]),
        ms(d[2]),
        ms(d[3])
    );
    println!(
        "codec - dense: {:.2} ms per iteration; codec / dense: {:.2}x (rendering and losses excluded)",
        ms(c[0] - d[0]),
        c[0] / d[0]
    );
    let record = format!(
        "{{\"strands\": {STRANDS}, \"sampled\": {SAMPLED}, \"points\": {POINTS}, \"feature_dim\": {}, \
         \"codec_ms\": {}, \"codec_forward_ms\": {}, \"codec_backward_ms\": {}, \"codec_step_ms\": {}, \
         \"dense_ms\": {}, \"dense_forward_ms\": {}, \"dense_backward_ms\": {}, \"dense_step_ms\": {}, \
         \"codec_over_dense\": {}}}\n",
        prep.feature_dim,
        ms(c[0]),
        ms(c[1]),
        ms(c[2]),
        ms(c[3]),
        ms(d[0]),
        ms(d[1]),
        ms(d[2]),
        ms(d[3]),
        c[0] / d[0]
    );
    let _ = std::fs::create_dir_all("target/bench");
    let _ = std::fs::write("target/bench/learn.json", record);
}
