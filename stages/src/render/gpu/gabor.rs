//! The Gabor orientation filtering of `orientation_maps` on the GPU
//! (`gabor.wgsl`, one thread per pixel): the host prepares what the CPU path
//! prepares (the mirror-padded difference-of-Gaussians image and the filter
//! bank as flat tap offsets, `growth/orientation.rs`) and the kernel does the
//! per-pixel work, the part that grows with orientations x taps x pixels.

use bytemuck::{Pod, Zeroable};

use super::{gpu_err, groups2, GpuRenderer};
use crate::render::RenderError;

/// `MAX_ORIENTATIONS` in gabor.wgsl (the responses kept per thread).
const MAX_ORIENTATIONS: usize = 360;

/// `GaborParams` in gabor.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GaborParams {
    width: u32,
    height: u32,
    pw: u32,
    half: u32,
    n: u32,
    has_mask: u32,
    pad0: u32,
    pad1: u32,
}

/// The image to filter: the DoG image mirror-padded by `half` on every side
/// (rows of `width + 2 half`), and the filter bank as taps (offset into the
/// padded image relative to the pixel, weight), filter by filter.
pub struct GaborInput<'a> {
    pub padded: &'a [f32],
    pub width: u32,
    pub height: u32,
    pub half: u32,
    pub bank: &'a [Vec<(isize, f32)>],
    /// Pixels below 0.5 are skipped (angle and confidence 0).
    pub mask: Option<&'a [f32]>,
}

impl GpuRenderer {
    /// Per pixel the angle of the strongest filter and the confidence
    /// (`growth::orientation::orientation_maps`' formulas), as two planes.
    pub fn gabor_maps(&self, inp: &GaborInput<'_>) -> Result<(Vec<f32>, Vec<f32>), RenderError> {
        let (w, h, half) = (inp.width, inp.height, inp.half);
        let pw = w + 2 * half;
        let npix = (w * h) as usize;
        if inp.padded.len() != (pw * (h + 2 * half)) as usize
            || inp.mask.is_some_and(|m| m.len() != npix)
            || inp.bank.is_empty()
        {
            return Err(gpu_err("gabor: inconsistent image, mask or bank sizes"));
        }
        if inp.bank.len() > MAX_ORIENTATIONS {
            return Err(gpu_err(format!(
                "gabor: {} orientations, the GPU path takes at most {MAX_ORIENTATIONS} \
                 (use device = \"cpu\" for more)",
                inp.bank.len()
            )));
        }
        let mut starts = vec![0u32];
        let (mut offs, mut wts) = (Vec::new(), Vec::new());
        for k in inp.bank {
            for &(o, wt) in k {
                offs.push(o as i32);
                wts.push(wt);
            }
            starts.push(offs.len() as u32);
        }
        if offs.is_empty() {
            // Every tap dropped: no response anywhere, as on the CPU.
            offs.push(0);
            wts.push(0.0);
        }
        let params = GaborParams {
            width: w,
            height: h,
            pw,
            half,
            n: inp.bank.len() as u32,
            has_mask: inp.mask.is_some() as u32,
            pad0: 0,
            pad1: 0,
        };
        let ones;
        let mask = match inp.mask {
            Some(m) => m,
            None => {
                ones = [1.0f32];
                &ones[..]
            }
        };
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let mut enc = self.encoder();
        let mut keep = Vec::new();
        let mut up = |label: &str, bytes: &[u8]| -> Result<_, RenderError> {
            let (b, s) = self.upload(&mut enc, label, bytes)?;
            keep.push(s);
            Ok(b)
        };
        let padded = up("gabor image", bytemuck::cast_slice(inp.padded))?;
        let tap_off = up("gabor tap offsets", bytemuck::cast_slice(&offs))?;
        let tap_w = up("gabor tap weights", bytemuck::cast_slice(&wts))?;
        let starts_b = up("gabor filter starts", bytemuck::cast_slice(&starts))?;
        let mask_b = up("gabor mask", bytemuck::cast_slice(mask))?;
        let maps = self.storage("gabor maps", npix as u64 * 8);
        let u = self.uniform(bytemuck::bytes_of(&params));
        self.dispatch(
            &mut enc,
            &self.kernels.gabor,
            &u,
            None,
            &[&padded, &tap_off, &tap_w, &starts_b, &mask_b, &maps],
            groups2((npix as u32).div_ceil(256)),
        );
        self.submit_wait(enc)?;
        drop(keep);
        self.read_with(&maps, 0, npix as u64 * 8, |b| {
            let v = super::as_f32(b);
            let orient = v.iter().step_by(2).copied().collect();
            let conf = v.iter().skip(1).step_by(2).copied().collect();
            (orient, conf)
        })
    }
}
