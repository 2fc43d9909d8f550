//! Tiling, depth sorting, front-to-back compositing and its adjoint.
//!
//! Work is split into 16x16 tiles, one rayon task per tile; inside a tile the
//! loop runs over the tile's depth-sorted Gaussians and, for each, over the
//! pixels inside its support ellipse only (row intervals solved from the
//! conic), keeping per-pixel transmittance and accumulators. The backward
//! pass runs the same loop back to front, recovering each transmittance by
//! division, and writes one gradient record per (tile, Gaussian) instance;
//! records are summed per Gaussian in instance (tile-major) order, so the
//! result does not depend on the thread count.

// `!(x > y)` is deliberate: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

use glam::Vec2;
use rayon::prelude::*;

use super::gaussians::{GaussianGrads, Gaussians};
use super::project::{
    project_backward, project_one, CamData, GaussianParams, Splat, SplatGrad, F_ALPHA, F_DEPTH,
    F_FUR, F_OX, F_OY, NF,
};
use super::{RenderError, RenderSettings, TILE};
use crate::data::camera::Camera;
use crate::data::image::ImageF32;

const TP: usize = (TILE * TILE) as usize;
/// Gaussians per rayon task in the per-Gaussian passes.
const CHUNK: usize = 4096;

/// The rendered images (see the [`crate::render`] module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOutput {
    /// 3 channels, linear RGB over the background.
    pub rgb: ImageF32,
    /// 1 channel, `1 - final transmittance`.
    pub alpha: ImageF32,
    /// 1 channel, alpha-blended view depth (not divided by alpha).
    pub depth: ImageF32,
    /// 2 channels, blended `((a - c), 2b) / (a + c)` of the 2D covariance.
    pub orientation: ImageF32,
    /// 1 channel, blended fur flag.
    pub fur: ImageF32,
}

impl RenderOutput {
    /// All outputs of a `w` x `h` view, zero.
    pub fn zeros(w: u32, h: u32) -> RenderOutput {
        RenderOutput {
            rgb: ImageF32::new(w, h, 3),
            alpha: ImageF32::new(w, h, 1),
            depth: ImageF32::new(w, h, 1),
            orientation: ImageF32::new(w, h, 2),
            fur: ImageF32::new(w, h, 1),
        }
    }
}

/// What [`backward`] needs from [`render`].
#[derive(Debug, Clone)]
pub struct RenderState {
    width: u32,
    height: u32,
    n_gaussians: usize,
    splats: Vec<Splat>,
    /// Gaussian index of every (tile, Gaussian) instance, tile-major, depth-sorted within a tile.
    instances: Vec<u32>,
    /// Instance range of every tile.
    tile_ranges: Vec<(u32, u32)>,
    /// Per pixel (row-major): final transmittance.
    t_final: Vec<f32>,
    /// Per pixel: 1 + the in-tile index of the last blended Gaussian (0 = none).
    n_contrib: Vec<u32>,
    /// Gaussian-pixel evaluations in the forward pass.
    pub evaluations: u64,
}

impl RenderState {
    /// Number of (tile, Gaussian) instances.
    pub fn instance_count(&self) -> usize {
        self.instances.len()
    }
    /// Number of Gaussians that survived culling.
    pub fn visible_count(&self) -> usize {
        self.splats.iter().filter(|s| s.visible).count()
    }
}

/// dL/d(output image); `None` means zero.
#[derive(Debug, Clone, Default)]
pub struct OutputGrads {
    pub rgb: Option<ImageF32>,
    pub alpha: Option<ImageF32>,
    pub depth: Option<ImageF32>,
    pub orientation: Option<ImageF32>,
    pub fur: Option<ImageF32>,
}

/// `ceil` for values clamped to +-1e6 (inline; libm's ceilf is a call
/// without SSE4.1).
#[inline(always)]
fn ceil_i(x: f32) -> i32 {
    let x = x.clamp(-1.0e6, 1.0e6);
    let i = x as i32;
    if (i as f32) < x {
        i + 1
    } else {
        i
    }
}

/// `floor` for values clamped to +-1e6.
#[inline(always)]
fn floor_i(x: f32) -> i32 {
    let x = x.clamp(-1.0e6, 1.0e6);
    let i = x as i32;
    if (i as f32) > x {
        i - 1
    } else {
        i
    }
}

/// Integer pixel interval of row `y` covered by the support ellipse (unclamped).
#[inline(always)]
fn row_span(sp: &Splat, y: i32) -> Option<(i32, i32)> {
    let [ca, cb, cc] = sp.conic;
    let dy = y as f32 + 0.5 - sp.mean.y;
    let disc = cb * cb * dy * dy - ca * (cc * dy * dy - sp.k2);
    if !(disc >= 0.0) {
        return None;
    }
    let sq = disc.sqrt();
    let inv = 1.0 / ca;
    let x0 = sp.mean.x + (-cb * dy - sq) * inv;
    let x1 = sp.mean.x + (-cb * dy + sq) * inv;
    let lo = ceil_i(x0 - 0.5);
    let hi = floor_i(x1 - 0.5);
    (lo <= hi).then_some((lo, hi))
}

/// Pixel rows covered by the support (unclamped).
#[inline(always)]
fn row_range(sp: &Splat) -> (i32, i32) {
    let ey = (sp.k2 * sp.cov[2]).sqrt();
    (ceil_i(sp.mean.y - ey - 0.5), floor_i(sp.mean.y + ey - 0.5))
}

/// Pixel columns covered by the support (unclamped).
#[inline(always)]
fn col_range(sp: &Splat) -> (i32, i32) {
    let ex = (sp.k2 * sp.cov[0]).sqrt();
    (ceil_i(sp.mean.x - ex - 0.5), floor_i(sp.mean.x + ex - 0.5))
}

/// Calls `f(tile_x, tile_y)` for every tile the support touches (exact for
/// the ellipse: per band of tile rows, the union of the row intervals).
#[inline]
fn for_each_tile(sp: &Splat, w: u32, h: u32, mut f: impl FnMut(u32, u32)) {
    let (r0, r1) = sp.rows;
    let (r0, r1) = (r0.max(0), r1.min(h as i32 - 1));
    let (c0, c1) = col_range(sp);
    let (c0, c1) = (c0.max(0), c1.min(w as i32 - 1));
    if r0 > r1 || c0 > c1 {
        return;
    }
    let t = TILE as i32;
    // Fast path: the bounding box lies in one tile (most strand segments).
    if r0 / t == r1 / t && c0 / t == c1 / t {
        // The ellipse may still miss the image part of the box; check rows.
        if (r0..=r1).any(|y| row_span(sp, y).is_some_and(|(a, b)| a.max(c0) <= b.min(c1))) {
            f((c0 / t) as u32, (r0 / t) as u32);
        }
        return;
    }
    let mut band = r0 / t;
    let (mut lo, mut hi) = (i32::MAX, i32::MIN);
    let flush = |band: i32, lo: i32, hi: i32, f: &mut dyn FnMut(u32, u32)| {
        if lo <= hi {
            for tx in lo / t..=hi / t {
                f(tx as u32, band as u32);
            }
        }
    };
    for y in r0..=r1 {
        if y / t != band {
            flush(band, lo, hi, &mut f);
            band = y / t;
            lo = i32::MAX;
            hi = i32::MIN;
        }
        if let Some((a, b)) = row_span(sp, y) {
            let (a, b) = (a.max(c0), b.min(c1));
            if a <= b {
                lo = lo.min(a);
                hi = hi.max(b);
            }
        }
    }
    flush(band, lo, hi, &mut f);
}

/// Alpha of a splat at pixel (x, y) and the Gaussian factor; `None` when skipped.
#[inline(always)]
fn eval(sp: &Splat, x: i32, y: i32, s: &RenderSettings) -> Option<(f32, f32, f32, f32, bool)> {
    let dx = x as f32 + 0.5 - sp.mean.x;
    let dy = y as f32 + 0.5 - sp.mean.y;
    let [ca, cb, cc] = sp.conic;
    let power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
    let gauss = power.min(0.0).exp();
    let raw = sp.opacity * gauss;
    let clamped = raw > s.alpha_max;
    let alpha = if clamped { s.alpha_max } else { raw };
    if alpha < s.alpha_min || !(alpha > 0.0) {
        return None;
    }
    Some((alpha, gauss, dx, dy, clamped))
}

/// `img` must be `w` x `h` x `ch` with that many values (the renderer's
/// inputs and output gradients; the losses' images).
pub(super) fn check_image(
    what: &'static str,
    img: &ImageF32,
    w: u32,
    h: u32,
    ch: u32,
) -> Result<(), RenderError> {
    if img.width != w
        || img.height != h
        || img.channels != ch
        || img.data.len() != (w * h * ch) as usize
    {
        return Err(RenderError::Image {
            what,
            width: w,
            height: h,
            channels: ch,
            found: format!(
                "{}x{}x{} ({} values)",
                img.width,
                img.height,
                img.channels,
                img.data.len()
            ),
        });
    }
    Ok(())
}

/// Renders `g` from `cam`. Returns the images and the state for [`backward`].
pub fn render(
    g: &Gaussians,
    cam: &Camera,
    s: &RenderSettings,
) -> Result<(RenderOutput, RenderState), RenderError> {
    let (w, h, splats, bins) = project_and_bin(g, cam, s)?;
    let tiles: Vec<TileOut> = (0..bins.tile_ranges.len())
        .into_par_iter()
        .map(|t| composite_tile(t, &bins, &splats, w, h, s))
        .collect();
    let (out, t_final, n_contrib, evaluations) = scatter(&tiles, bins.tiles_x, w, h, s);
    let state = RenderState {
        width: w,
        height: h,
        n_gaussians: g.len(),
        splats,
        instances: bins.instances,
        tile_ranges: bins.tile_ranges,
        t_final,
        n_contrib,
        evaluations,
    };
    Ok((out, state))
}

/// Steps 1 to 3 for a view of `g` from `cam` (inputs validated): the image
/// size, every Gaussian's splat and the splats binned by tile.
fn project_and_bin(
    g: &Gaussians,
    cam: &Camera,
    s: &RenderSettings,
) -> Result<(u32, u32, Vec<Splat>, TileBins), RenderError> {
    s.validate()?;
    g.validate()?;
    let cd = CamData::new(cam)?;
    let splats = project_all(g, &cd, s);
    let bins = bin_by_tile(&splats, cd.width, cd.height);
    Ok((cd.width, cd.height, splats, bins))
}

/// Step 1: projects every Gaussian (independent per Gaussian).
fn project_all(g: &Gaussians, cd: &CamData, s: &RenderSettings) -> Vec<Splat> {
    let mut splats = vec![Splat::default(); g.len()];
    splats
        .par_chunks_mut(CHUNK)
        .enumerate()
        .for_each(|(c, out)| {
            for (j, sp) in out.iter_mut().enumerate() {
                let i = c * CHUNK + j;
                *sp = project_one(GaussianParams::of(g, i), g.opacities[i], g.fur[i], cd, s);
                if sp.visible {
                    sp.rows = row_range(sp);
                }
            }
        });
    splats
}

/// The visible splats binned by tile: per tile a range of `instances`
/// (Gaussian indices in depth order).
struct TileBins {
    tiles_x: u32,
    instances: Vec<u32>,
    tile_ranges: Vec<(u32, u32)>,
}

/// Steps 2 and 3: the global depth order, then the tiles of every splat (in depth
/// order) and a stable counting sort by tile.
fn bin_by_tile(splats: &[Splat], w: u32, h: u32) -> TileBins {
    // Key (depth bits, index) is unique, so the order is total.
    let mut order: Vec<u64> = splats
        .iter()
        .enumerate()
        .filter(|(_, sp)| sp.visible)
        .map(|(i, sp)| ((sp.feat[F_DEPTH].to_bits() as u64) << 32) | i as u64)
        .collect();
    order.par_sort_unstable();
    let (tx, ty) = (w.div_ceil(TILE), h.div_ceil(TILE));
    let n_tiles = (tx * ty) as usize;
    // One pass per chunk of the depth order: tile ids and per-splat counts.
    let chunks: Vec<(Vec<u32>, Vec<u32>)> = order
        .par_chunks(CHUNK)
        .map(|ch| {
            let mut ids = Vec::with_capacity(ch.len() * 2);
            let mut counts = Vec::with_capacity(ch.len());
            for &k in ch {
                let before = ids.len();
                for_each_tile(&splats[(k & 0xffff_ffff) as usize], w, h, |x, y| {
                    ids.push(y * tx + x)
                });
                counts.push((ids.len() - before) as u32);
            }
            (ids, counts)
        })
        .collect();
    let total: usize = chunks.iter().map(|c| c.0.len()).sum();
    let mut offsets = Vec::with_capacity(order.len() + 1);
    offsets.push(0usize);
    for (_, counts) in &chunks {
        for &c in counts {
            let last = *offsets.last().unwrap_or(&0);
            offsets.push(last + c as usize);
        }
    }
    let mut inst_tile = Vec::with_capacity(total);
    for (ids, _) in &chunks {
        inst_tile.extend_from_slice(ids);
    }
    drop(chunks);
    let mut tile_count = vec![0u32; n_tiles + 1];
    for &t in &inst_tile {
        tile_count[t as usize + 1] += 1;
    }
    for t in 0..n_tiles {
        tile_count[t + 1] += tile_count[t];
    }
    let tile_ranges: Vec<(u32, u32)> = (0..n_tiles)
        .map(|t| (tile_count[t], tile_count[t + 1]))
        .collect();
    let mut cursor = tile_count;
    let mut instances = vec![0u32; total];
    for (si, &k) in order.iter().enumerate() {
        let gi = (k & 0xffff_ffff) as u32;
        for &t in &inst_tile[offsets[si]..offsets[si + 1]] {
            instances[cursor[t as usize] as usize] = gi;
            cursor[t as usize] += 1;
        }
    }
    TileBins {
        tiles_x: tx,
        instances,
        tile_ranges,
    }
}

/// Tile `t`'s pixel rectangle `[x0, x1) x [y0, y1)` in a `w` x `h` image
/// `tx` tiles wide.
fn tile_rect(t: usize, tx: u32, w: u32, h: u32) -> (i32, i32, i32, i32) {
    let (x0, y0) = ((t as u32 % tx) * TILE, (t as u32 / tx) * TILE);
    let (x1, y1) = ((x0 + TILE).min(w) as i32, (y0 + TILE).min(h) as i32);
    (x0 as i32, y0 as i32, x1, y1)
}

/// A tile's splats, gathered first: independent loads overlap their cache
/// misses, and the loops over them then read sequentially.
fn gather(splats: &[Splat], instances: &[u32]) -> Vec<Splat> {
    instances.iter().map(|&gi| splats[gi as usize]).collect()
}

/// Calls `f(x, y, p)` for every pixel of the tile rectangle `rect` (see
/// [`tile_rect`]) in splat `sp`'s rows and row spans, row by row; `p` is the
/// pixel's index in the tile.
#[inline(always)]
fn for_each_covered(
    sp: &Splat,
    (x0, y0, x1, y1): (i32, i32, i32, i32),
    mut f: impl FnMut(i32, i32, usize),
) {
    let (r0, r1) = sp.rows;
    for y in r0.max(y0)..=r1.min(y1 - 1) {
        let Some((c0, c1)) = row_span(sp, y) else {
            continue;
        };
        for x in c0.max(x0)..=c1.min(x1 - 1) {
            f(x, y, ((y - y0) as u32 * TILE + (x - x0) as u32) as usize);
        }
    }
}

/// One tile's accumulated features, transmittance and contributor counts
/// (tile-local pixel order).
struct TileOut {
    acc: Vec<[f32; NF]>,
    t: Vec<f32>,
    nc: Vec<u32>,
    evals: u64,
}

/// Step 4: front-to-back compositing of tile `t`'s splats.
fn composite_tile(
    t: usize,
    bins: &TileBins,
    splats: &[Splat],
    w: u32,
    h: u32,
    s: &RenderSettings,
) -> TileOut {
    let mut acc = vec![[0.0f32; NF]; TP];
    let mut nc = vec![0u32; TP];
    let (tr, evals) = composite_tile_with(t, bins, splats, w, h, s, |k, sp, p, wgt| {
        for c in 0..NF {
            acc[p][c] += sp.feat[c] * wgt;
        }
        nc[p] = k as u32 + 1;
    });
    TileOut {
        acc,
        t: tr,
        nc,
        evals,
    }
}

/// The compositing loop of tile `t`, front to back: calls `blend(k, splat,
/// p, alpha T)` for every splat blended into tile pixel `p` (`k` its index
/// in the tile's list), in blending order. Returns the tile's final
/// transmittance and its Gaussian-pixel evaluations.
#[inline(always)]
fn composite_tile_with(
    t: usize,
    bins: &TileBins,
    splats: &[Splat],
    w: u32,
    h: u32,
    s: &RenderSettings,
    mut blend: impl FnMut(usize, &Splat, usize, f32),
) -> (Vec<f32>, u64) {
    let rect = tile_rect(t, bins.tiles_x, w, h);
    let (x0, y0, x1, y1) = rect;
    let npix = ((x1 - x0) * (y1 - y0)) as usize;
    let mut tr = vec![1.0f32; TP];
    let mut done = [false; TP];
    let mut n_done = 0usize;
    let mut evals = 0u64;
    let (a, b) = bins.tile_ranges[t];
    let recs = gather(splats, &bins.instances[a as usize..b as usize]);
    for (k, sp) in recs.iter().enumerate() {
        for_each_covered(sp, rect, |x, y, p| {
            if done[p] {
                return;
            }
            evals += 1;
            let Some((alpha, ..)) = eval(sp, x, y, s) else {
                return;
            };
            let tn = tr[p] * (1.0 - alpha);
            if tn < s.transmittance_min {
                done[p] = true;
                n_done += 1;
                return;
            }
            blend(k, sp, p, alpha * tr[p]);
            tr[p] = tn;
        });
        if n_done == npix {
            break;
        }
    }
    (tr, evals)
}

/// Per Gaussian, its blending weights `alpha_i T_i` summed over the pixels
/// of a view of `g` from `cam`, weighted by two images: `target` (3
/// channels) and `pixel_weight` (1 channel), as `[sum w t_r, sum w t_g, sum
/// w t_b, sum w pixel_weight]`.
///
/// These are the colour gradients of the linear losses `sum_p target_p .
/// rgb_p` and `sum_p pixel_weight_p (r + g + b)_p / 3` (before the SH
/// factor), which a colour fit needs, computed in one front-to-back pass
/// instead of a render and two backward passes. Sums are taken per (tile,
/// Gaussian) instance and then per Gaussian in instance order, so the result
/// does not depend on the thread count.
pub fn blend_sums(
    g: &Gaussians,
    cam: &Camera,
    s: &RenderSettings,
    target: &ImageF32,
    pixel_weight: &ImageF32,
) -> Result<Vec<[f32; 4]>, RenderError> {
    check_blend_images(target, pixel_weight, cam.width, cam.height)?;
    let (w, h, splats, bins) = project_and_bin(g, cam, s)?;
    let tiles: Vec<Vec<[f32; 4]>> = (0..bins.tile_ranges.len())
        .into_par_iter()
        .map(|t| {
            let (x0, y0, x1, y1) = tile_rect(t, bins.tiles_x, w, h);
            let mut px = [[0.0f32; 4]; TP];
            for y in y0..y1 {
                for x in x0..x1 {
                    let p = ((y - y0) as u32 * TILE + (x - x0) as u32) as usize;
                    let q = (y as u32 * w + x as u32) as usize;
                    let rgb = &target.data[3 * q..3 * q + 3];
                    px[p] = [rgb[0], rgb[1], rgb[2], pixel_weight.data[q]];
                }
            }
            let (a, b) = bins.tile_ranges[t];
            let mut sums = vec![[0.0f32; 4]; (b - a) as usize];
            composite_tile_with(t, &bins, &splats, w, h, s, |k, _, p, wgt| {
                for c in 0..4 {
                    sums[k][c] += px[p][c] * wgt;
                }
            });
            sums
        })
        .collect();
    let mut out = vec![[0.0f32; 4]; g.len()];
    for (&gi, inst) in bins.instances.iter().zip(tiles.iter().flatten()) {
        for c in 0..4 {
            out[gi as usize][c] += inst[c];
        }
    }
    Ok(out)
}

/// The images of [`blend_sums`] (shared with the GPU path): `target` 3
/// channels and `pixel_weight` 1, both `w` x `h`, every value finite.
pub(crate) fn check_blend_images(
    target: &ImageF32,
    pixel_weight: &ImageF32,
    w: u32,
    h: u32,
) -> Result<(), RenderError> {
    check_image("blend target", target, w, h, 3)?;
    check_image("blend pixel weight", pixel_weight, w, h, 1)?;
    for (what, img) in [
        ("blend target", target),
        ("blend pixel weight", pixel_weight),
    ] {
        if let Some(index) = img.data.iter().position(|v| !v.is_finite()) {
            return Err(RenderError::NonFinite { what, index });
        }
    }
    Ok(())
}

/// Step 5: scatters the tiles into the images; also the final transmittance,
/// contributor count per pixel and the evaluation count.
fn scatter(
    tiles: &[TileOut],
    tx: u32,
    w: u32,
    h: u32,
    s: &RenderSettings,
) -> (RenderOutput, Vec<f32>, Vec<u32>, u64) {
    let mut out = RenderOutput::zeros(w, h);
    let mut t_final = vec![1.0f32; (w * h) as usize];
    let mut n_contrib = vec![0u32; (w * h) as usize];
    let mut evaluations = 0u64;
    let bg = s.background;
    for (t, to) in tiles.iter().enumerate() {
        evaluations += to.evals;
        let (x0, y0) = ((t as u32 % tx) * TILE, (t as u32 / tx) * TILE);
        for y in y0..(y0 + TILE).min(h) {
            for x in x0..(x0 + TILE).min(w) {
                let p = ((y - y0) * TILE + (x - x0)) as usize;
                let q = (y * w + x) as usize;
                let (a, tr) = (&to.acc[p], to.t[p]);
                out.rgb.data[3 * q] = a[0] + tr * bg.x;
                out.rgb.data[3 * q + 1] = a[1] + tr * bg.y;
                out.rgb.data[3 * q + 2] = a[2] + tr * bg.z;
                out.alpha.data[q] = 1.0 - tr;
                out.depth.data[q] = a[F_DEPTH];
                out.orientation.data[2 * q] = a[F_OX];
                out.orientation.data[2 * q + 1] = a[F_OY];
                out.fur.data[q] = a[F_FUR];
                t_final[q] = tr;
                n_contrib[q] = to.nc[p];
            }
        }
    }
    (out, t_final, n_contrib, evaluations)
}

/// Checks that the camera and the Gaussians are the ones the render state
/// was made with, and that the Gaussians are valid.
fn check_backward_inputs(g: &Gaussians, cd: &CamData, st: &RenderState) -> Result<(), RenderError> {
    check_matches_state(g.len(), cd, (st.width, st.height), st.n_gaussians)?;
    g.validate()?;
    Ok(())
}

/// Checks a backward pass's camera size and Gaussian count against those
/// of its render state (`size`, `n`); shared with the GPU path.
pub(crate) fn check_matches_state(
    n_gaussians: usize,
    cd: &CamData,
    size: (u32, u32),
    n: usize,
) -> Result<(), RenderError> {
    let (w, h) = size;
    if cd.width != w || cd.height != h {
        return Err(RenderError::Camera(format!(
            "camera is {}x{} but the render state is {w}x{h}",
            cd.width, cd.height
        )));
    }
    if n_gaussians != n {
        return Err(RenderError::Length {
            what: "gaussians (vs the render state)",
            expected: n,
            found: n_gaussians,
        });
    }
    Ok(())
}

/// The per-pixel output gradients in feature layout (absent images: zero),
/// checked for size and finiteness.
fn pixel_grads(dl: &OutputGrads, w: u32, h: u32) -> Result<Vec<[f32; NF]>, RenderError> {
    let mut gpix = vec![[0.0f32; NF]; (w * h) as usize];
    let chans: [(&Option<ImageF32>, &'static str, u32, usize); 5] = [
        (&dl.rgb, "rgb gradient", 3, 0),
        (&dl.alpha, "alpha gradient", 1, F_ALPHA),
        (&dl.depth, "depth gradient", 1, F_DEPTH),
        (&dl.orientation, "orientation gradient", 2, F_OX),
        (&dl.fur, "fur gradient", 1, F_FUR),
    ];
    for (img, what, ch, f0) in chans {
        if let Some(img) = img {
            check_image(what, img, w, h, ch)?;
            for (q, gp) in gpix.iter_mut().enumerate() {
                for c in 0..ch as usize {
                    let v = img.data[q * ch as usize + c];
                    if !v.is_finite() {
                        return Err(RenderError::NonFinite { what, index: q });
                    }
                    gp[f0 + c] = v;
                }
            }
        }
    }
    Ok(gpix)
}

/// Splits the per-instance gradients into one disjoint slice per tile.
fn tile_slices<'a>(
    inst: &'a mut [SplatGrad],
    tile_ranges: &[(u32, u32)],
) -> Vec<&'a mut [SplatGrad]> {
    let mut slices = Vec::with_capacity(tile_ranges.len());
    let mut rest: &mut [SplatGrad] = inst;
    for &(a, b) in tile_ranges {
        let (head, tail) = rest.split_at_mut((b - a) as usize);
        slices.push(head);
        rest = tail;
    }
    slices
}

/// The screen-space gradient of every (tile, Gaussian) instance: per tile
/// (in parallel), its splats back to front over its pixels, undoing the
/// compositing from the final transmittance.
fn instance_grads(st: &RenderState, gpix: &[[f32; NF]], s: &RenderSettings) -> Vec<SplatGrad> {
    let (w, h) = (st.width, st.height);
    let tx = w.div_ceil(TILE);
    let bg = s.background;
    let mut inst = vec![SplatGrad::default(); st.instances.len()];
    let slices = tile_slices(&mut inst, &st.tile_ranges);
    slices.into_par_iter().enumerate().for_each(|(t, out)| {
        let rect = tile_rect(t, tx, w, h);
        let (x0, y0, x1, y1) = rect;
        let mut tr = [0.0f32; TP];
        let mut sacc = [[0.0f32; NF]; TP];
        let mut gp = [[0.0f32; NF]; TP];
        let mut nc = [0u32; TP];
        for y in y0..y1 {
            for x in x0..x1 {
                let p = ((y - y0) as u32 * TILE + (x - x0) as u32) as usize;
                let q = (y as u32 * w + x as u32) as usize;
                tr[p] = st.t_final[q];
                sacc[p][0] = bg.x * tr[p];
                sacc[p][1] = bg.y * tr[p];
                sacc[p][2] = bg.z * tr[p];
                gp[p] = gpix[q];
                nc[p] = st.n_contrib[q];
            }
        }
        let (a, _) = st.tile_ranges[t];
        let recs = gather(
            &st.splats,
            &st.instances[a as usize..a as usize + out.len()],
        );
        for k in (0..recs.len()).rev() {
            let sp = &recs[k];
            let [ca, cb, cc] = sp.conic;
            let mut gr = SplatGrad::default();
            for_each_covered(sp, rect, |x, y, p| {
                if k as u32 >= nc[p] {
                    return;
                }
                let Some((alpha, gauss, dx, dy, clamped)) = eval(sp, x, y, s) else {
                    return;
                };
                let inv_one_m = 1.0 / (1.0 - alpha);
                let ti = tr[p] * inv_one_m;
                let wgt = alpha * ti;
                let mut dalpha = 0.0f32;
                for c in 0..NF {
                    dalpha += gp[p][c] * (sp.feat[c] * ti - sacc[p][c] * inv_one_m);
                    gr.feat[c] += gp[p][c] * wgt;
                    sacc[p][c] += sp.feat[c] * wgt;
                }
                tr[p] = ti;
                if !clamped {
                    gr.opacity += dalpha * gauss;
                    let dp = dalpha * alpha;
                    gr.mean[0] += dp * (ca * dx + cb * dy);
                    gr.mean[1] += dp * (cb * dx + cc * dy);
                    gr.conic[0] += -0.5 * dp * dx * dx;
                    gr.conic[1] += -dp * dx * dy;
                    gr.conic[2] += -0.5 * dp * dy * dy;
                }
            });
            out[k] = gr;
        }
    });
    inst
}

/// Sums the instances' gradients per Gaussian in instance order (deterministic).
fn sum_per_gaussian(st: &RenderState, inst: Vec<SplatGrad>, n: usize) -> Vec<SplatGrad> {
    let mut acc = vec![SplatGrad::default(); n];
    for (j, &gi) in st.instances.iter().enumerate() {
        acc[gi as usize].add(&inst[j]);
    }
    acc
}

/// The projection's adjoint, independent per Gaussian (in chunks): the
/// parameter gradients from the summed screen-space ones `acc`.
fn projection_adjoint(
    g: &Gaussians,
    st: &RenderState,
    acc: &[SplatGrad],
    cd: &CamData,
    s: &RenderSettings,
) -> GaussianGrads {
    let mut out = GaussianGrads::zeros(g.len());
    let n = g.len();
    let parts: Vec<Vec<super::project::ParamGrad>> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            (c * CHUNK..((c + 1) * CHUNK).min(n))
                .map(|i| project_backward(GaussianParams::of(g, i), &st.splats[i], &acc[i], cd, s))
                .collect()
        })
        .collect();
    for (i, pg) in parts.into_iter().flatten().enumerate() {
        out.means[i] = pg.mean;
        out.scales[i] = pg.scale;
        out.rotations[i] = pg.rot;
        out.opacities[i] = pg.opacity;
        out.sh[i] = pg.sh;
        out.cov3d[i] = pg.cov3d;
        out.means2d[i] = Vec2::new(acc[i].mean[0], acc[i].mean[1]);
    }
    out
}

/// Gradients of all Gaussian parameters given dL/d(outputs). `g`, `cam` and
/// `s` must be the ones `st` was rendered with.
pub fn backward(
    g: &Gaussians,
    cam: &Camera,
    s: &RenderSettings,
    st: &RenderState,
    dl: &OutputGrads,
) -> Result<GaussianGrads, RenderError> {
    s.validate()?;
    let cd = CamData::new(cam)?;
    check_backward_inputs(g, &cd, st)?;
    let gpix = pixel_grads(dl, st.width, st.height)?;
    let inst = instance_grads(st, &gpix, s);
    let acc = sum_per_gaussian(st, inst, g.len());
    Ok(projection_adjoint(g, st, &acc, &cd, s))
}

#[cfg(test)]
impl RenderState {
    pub(crate) fn splats_visible(&self, i: usize) -> bool {
        self.splats[i].visible
    }
}
