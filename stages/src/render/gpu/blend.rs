//! The colour fits' per-Gaussian blend sums on the GPU
//! ([`crate::render::blend_sums`]): a render without image readback, then
//! `blend.wgsl` (a workgroup per tile, front to back with the forward
//! kernel's arithmetic, each instance's four sums reduced in workgroup
//! memory in a fixed order into its slot) and `blend_gather.wgsl` (per
//! Gaussian, its slots in tile order). Only the sums come back: 4 f32 per
//! Gaussian, against a render and two backward passes with 32 f32 per
//! Gaussian each before. Always the slot layout (no atomic mode): 16 bytes
//! per instance, and the same bits on every run.

use super::{groups2, GpuRenderer};
use crate::data::camera::Camera;
use crate::data::image::ImageF32;
use crate::render::gaussians::Gaussians;
use crate::render::raster::check_blend_images;
use crate::render::{RenderError, RenderSettings};

impl GpuRenderer {
    /// Per Gaussian `[sum w t_r, sum w t_g, sum w t_b, sum w pixel_weight]`
    /// over the view's pixels, `w = alpha T` its blending weight, as
    /// [`crate::render::blend_sums`] (within the parity tolerances of
    /// docs/gpu.md; the per-instance sums are added in another order).
    pub fn blend_sums(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        target: &ImageF32,
        pixel_weight: &ImageF32,
    ) -> Result<Vec<[f32; 4]>, RenderError> {
        check_blend_images(target, pixel_weight, cam.width, cam.height)?;
        let (_, st) = self.render_state(g, cam, s, false)?;
        let (n, n_inst, params) = (st.n, st.n_inst, st.params);
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let mut enc = self.encoder();
        let (pix, staging) = {
            let mut packed = self.scratch.lock().unwrap_or_else(|e| e.into_inner());
            packed.clear();
            packed.extend(
                target
                    .data
                    .chunks_exact(3)
                    .zip(&pixel_weight.data)
                    .flat_map(|(rgb, &wt)| [rgb[0], rgb[1], rgb[2], wt]),
            );
            self.upload(&mut enc, "blend pixels", bytemuck::cast_slice(&packed))?
        };
        let rec = self.storage("blend instance sums", n_inst.max(1) as u64 * 16);
        let sums = self.storage("blend sums", n.max(1) as u64 * 16);
        let u = self.uniform(bytemuck::bytes_of(&params));
        enc.clear_buffer(&rec, 0, None);
        self.dispatch(
            &mut enc,
            &self.kernels.blend,
            &u,
            None,
            &[&st.splats, &st.keys, &st.ranges, &pix, &st.ncontrib, &rec],
            (params.tiles_x, params.tiles_y),
        );
        self.dispatch(
            &mut enc,
            &self.kernels.blend_gather,
            &u,
            None,
            &[&st.offsets, &rec, &sums],
            groups2((n as u32).div_ceil(256)),
        );
        self.submit_wait(enc)?;
        drop(staging);
        self.read_with(&sums, 0, n as u64 * 16, |b| {
            super::as_f32(b)
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect()
        })
    }
}
