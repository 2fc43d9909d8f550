// Shared by the compositing kernels (`forward`, `backward`, `blend`: one
// 16x16 workgroup per tile, one thread per pixel), prepended after
// common.wgsl; they all bind the renderer's `P: Params`.

// The pixel a thread owns and its tile.
struct TilePixel {
    tile: u32,
    x: i32,
    y: i32,
    inside: bool,
}

fn tile_pixel(wid: vec3<u32>, lid3: vec3<u32>) -> TilePixel {
    let x = i32(wid.x * TILE + lid3.x);
    let y = i32(wid.y * TILE + lid3.y);
    return TilePixel(wid.x + wid.y * P.tiles_x, x, y, x < i32(P.width) && y < i32(P.height));
}

// Whether pixel (x, y) lies in a splat's support (raster.rs for_each_covered):
// its rows `bits(b.w) ..= bits(row1)`, then that row's span.
fn covers(a: vec4<f32>, b: vec4<f32>, row1: f32, x: i32, y: i32) -> bool {
    if y < bitcast<i32>(b.w) || y > bitcast<i32>(row1) {
        return false;
    }
    let s = row_span(a.xy, a.z, a.w, b.x, b.z, y);
    return x >= s.x && x <= s.y;
}

// A splat's Gaussian falloff at the pixel centre (px, py) (raster.rs eval);
// alpha is `opacity (b.y) x falloff` clamped at alpha_max.
fn falloff(a: vec4<f32>, b: vec4<f32>, px: f32, py: f32) -> f32 {
    let dx = px - a.x;
    let dy = py - a.y;
    let power = -0.5 * (a.z * dx * dx + b.x * dy * dy) - a.w * dx * dy;
    return exp(min(power, 0.0));
}

