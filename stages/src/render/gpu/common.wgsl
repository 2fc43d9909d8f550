// Shared declarations of the renderer's kernels (prepended to every kernel
// file). Every formula mirrors the CPU reference in `render/project.rs` and
// `render/raster.rs` one to one; see docs/gpu.md.

const TILE: u32 = 16u;
const TP: u32 = 256u;

// Camera and settings, one uniform per render (layout = `gpu::Params`).
struct Params {
    w0: vec4<f32>,
    w1: vec4<f32>,
    w2: vec4<f32>,
    tw: vec4<f32>,
    center: vec4<f32>,
    bg: vec4<f32>,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    rx_lo: f32,
    rx_hi: f32,
    ry_lo: f32,
    ry_hi: f32,
    near: f32,
    alpha_min: f32,
    alpha_max: f32,
    t_min: f32,
    extent: f32,
    low_pass: f32,
    width: u32,
    height: u32,
    n: u32,
    sh_degree: u32,
    tiles_x: u32,
    tiles_y: u32,
    n_inst: u32,
    mode: u32,
    pad0: u32,
    pad1: u32,
}

// Per-dispatch scalars of the scan, padding and sort kernels.
struct Small {
    n: u32,
    a: u32,
    b: u32,
    c: u32,
}

// A projected Gaussian (layout = `gpu::GpuSplat`, 80 bytes).
// a = (mean.x, mean.y, conic A, conic B); b = (conic C, opacity, k2, bits(row0));
// f0 = (r, g, b, bits(row1)); f1 = (depth, ox, oy, fur); cov = (a, b, c, bits(flags)).
// flags: bit 0 visible, bits 1..3 the RGB channels clamped at 0.
struct Splat {
    a: vec4<f32>,
    b: vec4<f32>,
    f0: vec4<f32>,
    f1: vec4<f32>,
    cov: vec4<f32>,
}

fn lin_id(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * 256u;
}

fn is_finite_f(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// `ceil` / `floor` for values clamped to +-1e6 (raster.rs ceil_i, floor_i).
fn ceil_i(x0: f32) -> i32 {
    let x = clamp(x0, -1.0e6, 1.0e6);
    let i = i32(x);
    if f32(i) < x {
        return i + 1;
    }
    return i;
}

fn floor_i(x0: f32) -> i32 {
    let x = clamp(x0, -1.0e6, 1.0e6);
    let i = i32(x);
    if f32(i) > x {
        return i - 1;
    }
    return i;
}

// Integer pixel interval of row y inside the support ellipse (raster.rs
// row_span); returns (lo, hi) with lo > hi when empty.
fn row_span(mean: vec2<f32>, ca: f32, cb: f32, cc: f32, k2: f32, y: i32) -> vec2<i32> {
    let dy = f32(y) + 0.5 - mean.y;
    let disc = cb * cb * dy * dy - ca * (cc * dy * dy - k2);
    if !(disc >= 0.0) {
        return vec2<i32>(1, 0);
    }
    let sq = sqrt(disc);
    let inv = 1.0 / ca;
    let x0 = mean.x + (-cb * dy - sq) * inv;
    let x1 = mean.x + (-cb * dy + sq) * inv;
    return vec2<i32>(ceil_i(x0 - 0.5), floor_i(x1 - 0.5));
}

// The instance keys' order (`sort`, `sort_local`): tile, then depth bits,
// then Gaussian index (the slot, .w, never decides: the first three are unique).
fn key_less(a: vec4<u32>, b: vec4<u32>) -> bool {
    if a.x != b.x {
        return a.x < b.x;
    }
    if a.y != b.y {
        return a.y < b.y;
    }
    return a.z < b.z;
}
