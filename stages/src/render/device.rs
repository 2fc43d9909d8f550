//! Which device renders: the `device` parameter of the rendering stages
//! (`frosting`, `codec_strands`, `dense_strands`, `evaluate`) and the
//! dispatch between the CPU reference and the GPU path (feature `gpu`,
//! docs/gpu.md).
//!
//! `cpu` (also when the parameter is unset) is the reference renderer; `gpu` needs the feature and
//! an adapter and is an error otherwise; `auto` takes the GPU when the
//! feature is compiled and an adapter exists, else the CPU. The parameter
//! enters the stage key like any other: GPU and CPU results agree within the
//! parity tolerances but not bit for bit, so they must not share a cache
//! entry. The device that ran is written to the stage's metrics.json
//! ([`Renderer::metrics`]).

use fure_stage_api::{ParamSpec, ParamType, Params, StageError};
use serde_json::{json, Value};

use super::gaussians::{GaussianGrads, Gaussians};
use super::raster::{OutputGrads, RenderOutput, RenderState};
use super::{RenderError, RenderSettings};
use crate::data::camera::Camera;
use crate::data::image::ImageF32;

/// The values of the `device` parameter.
pub const DEVICE_CHOICES: &[&str] = &["auto", "cpu", "gpu"];

/// The `device` parameter, declared the same way by every rendering stage.
/// Optional: unset means `cpu` and leaves the stage key as it was before the
/// parameter existed; a set value enters the key.
pub fn device_param() -> ParamSpec {
    ParamSpec::optional(
        "device",
        ParamType::Str,
        "where the Gaussian renderer runs: cpu (the reference, also when unset), gpu (wgpu; \
         needs the `gpu` feature and an adapter), auto (gpu when available, else cpu); a set \
         value enters the key (docs/gpu.md)",
    )
    .choices(DEVICE_CHOICES)
}

/// The renderer a stage uses: the CPU reference or the shared GPU device.
#[derive(Debug, Clone)]
pub enum Renderer {
    Cpu,
    #[cfg(feature = "gpu")]
    Gpu(std::sync::Arc<super::gpu::GpuRenderer>),
}

/// The forward state of either renderer.
#[derive(Debug)]
pub enum State {
    Cpu(RenderState),
    /// Boxed: the GPU state (buffers, readbacks) is much larger than the CPU's.
    #[cfg(feature = "gpu")]
    Gpu(Box<super::gpu::GpuState>),
}

impl State {
    /// Gaussian-pixel evaluations of the forward pass.
    pub fn evaluations(&self) -> u64 {
        match self {
            State::Cpu(s) => s.evaluations,
            #[cfg(feature = "gpu")]
            State::Gpu(s) => s.evaluations,
        }
    }
}

impl Renderer {
    /// The renderer for a `device` value (see the module doc).
    pub fn from_choice(choice: &str) -> Result<Renderer, String> {
        match choice {
            "cpu" => Ok(Renderer::Cpu),
            "gpu" => Self::gpu(),
            "auto" => Ok(Self::gpu().unwrap_or(Renderer::Cpu)),
            o => Err(format!("unknown device {o:?} (expected auto, cpu or gpu)")),
        }
    }

    /// The renderer for a stage's `device` parameter.
    pub fn from_params(p: &Params) -> Result<Renderer, StageError> {
        let choice = p.get("device").and_then(|v| v.as_str()).unwrap_or("cpu");
        Self::from_choice(choice).map_err(|e| StageError::param("device", e))
    }

    #[cfg(feature = "gpu")]
    fn gpu() -> Result<Renderer, String> {
        super::gpu::GpuRenderer::shared().map(Renderer::Gpu)
    }

    #[cfg(not(feature = "gpu"))]
    fn gpu() -> Result<Renderer, String> {
        Err("this fure was built without the `gpu` feature \
             (build with `cargo build --release --features gpu`)"
            .into())
    }

    /// "cpu" or "gpu".
    pub fn name(&self) -> &'static str {
        match self {
            Renderer::Cpu => "cpu",
            #[cfg(feature = "gpu")]
            Renderer::Gpu(_) => "gpu",
        }
    }

    /// The adapter's name on the GPU; None on the CPU.
    pub fn adapter(&self) -> Option<String> {
        match self {
            Renderer::Cpu => None,
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => Some(r.adapter_name().to_string()),
        }
    }

    /// `cpu`, or `gpu (ADAPTER)`: the stages' note for the run report.
    pub fn describe(&self) -> String {
        match self.adapter() {
            Some(a) => format!("{} ({a})", self.name()),
            None => self.name().to_string(),
        }
    }

    /// `{"device": ..., "adapter": ...}` for metrics.json.
    pub fn metrics(&self) -> Value {
        json!({"device": self.name(), "adapter": self.adapter()})
    }

    /// [`super::render`] on this device.
    pub fn render(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
    ) -> Result<(RenderOutput, State), RenderError> {
        match self {
            Renderer::Cpu => super::render(g, cam, s).map(|(o, st)| (o, State::Cpu(st))),
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => r
                .render(g, cam, s)
                .map(|(o, st)| (o, State::Gpu(Box::new(st)))),
        }
    }

    /// [`super::losses::l1_dssim`] with its SSIM term on this device (the
    /// L1 term is cheap and stays on the CPU).
    pub fn l1_dssim(
        &self,
        img: &ImageF32,
        target: &ImageF32,
        mask: Option<&ImageF32>,
        lambda: f32,
    ) -> Result<(f32, ImageF32), RenderError> {
        match self {
            Renderer::Cpu => super::losses::l1_dssim(img, target, mask, lambda),
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => {
                super::losses::l1_dssim_with(img, target, mask, lambda, |a, b, m| r.ssim(a, b, m))
            }
        }
    }

    /// [`super::backward`] on this device (`st` must come from this renderer).
    pub fn backward(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        st: &State,
        dl: &OutputGrads,
    ) -> Result<GaussianGrads, RenderError> {
        match (self, st) {
            (Renderer::Cpu, State::Cpu(st)) => super::backward(g, cam, s, st, dl),
            #[cfg(feature = "gpu")]
            (Renderer::Gpu(r), State::Gpu(st)) => r.backward(g, cam, s, st, dl),
            #[cfg(feature = "gpu")]
            _ => Err(RenderError::Gpu(
                "backward with a render state of the other device".into(),
            )),
        }
    }
}

impl Renderer {
    /// [`super::blend_sums`] on this device: the CPU's one compositing pass,
    /// or the GPU's `blend` kernels (`render/gpu/blend.rs`).
    pub fn blend_sums(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        target: &ImageF32,
        pixel_weight: &ImageF32,
    ) -> Result<Vec<[f32; 4]>, RenderError> {
        match self {
            Renderer::Cpu => super::blend_sums(g, cam, s, target, pixel_weight),
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => r.blend_sums(g, cam, s, target, pixel_weight),
        }
    }

    /// The sums of [`super::blend_sums`] as colour gradients (what they
    /// mean, and how they were taken before; the tests and the render bench
    /// compare against it): a render and two backward passes with `target` and then `pixel_weight` (on every
    /// channel) as the RGB output gradient, read from the degree-0 SH
    /// gradients. The colours are set to grey first, so that no clamp at 0
    /// zeroes a gradient and the gradients are the sums exactly.
    pub fn blend_sums_by_backward(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        target: &ImageF32,
        pixel_weight: &ImageF32,
    ) -> Result<Vec<[f32; 4]>, RenderError> {
        super::raster::check_image(
            "blend pixel weight",
            pixel_weight,
            target.width,
            target.height,
            1,
        )?;
        let mut grey = g.clone();
        for sh in &mut grey.sh {
            *sh = [glam::Vec3::ZERO; 4];
        }
        let (_, state) = self.render(&grey, cam, s)?;
        let weight3 = ImageF32 {
            width: pixel_weight.width,
            height: pixel_weight.height,
            channels: 3,
            data: pixel_weight.data.iter().flat_map(|&v| [v; 3]).collect(),
        };
        let mut sums = vec![[0.0f32; 4]; g.len()];
        for (c, img) in [target, &weight3].into_iter().enumerate() {
            let dl = OutputGrads {
                rgb: Some(img.clone()),
                ..Default::default()
            };
            let gg = self.backward(&grey, cam, s, &state, &dl)?;
            for (out, sh) in sums.iter_mut().zip(&gg.sh) {
                let v = sh[0] / super::SH_C0;
                if c == 0 {
                    out[..3].copy_from_slice(&v.to_array());
                } else {
                    out[3] = (v.x + v.y + v.z) / 3.0;
                }
            }
        }
        Ok(sums)
    }
}

/// One view's targets for [`Renderer::image_step`]: the colour, and what
/// the view has of the rest.
#[derive(Debug, Clone, Copy)]
pub struct ViewTargets<'a> {
    /// 3 channels.
    pub rgb: &'a ImageF32,
    /// Silhouette mask (1 channel).
    pub mask: Option<&'a ImageF32>,
    /// Fur mask (1 channel).
    pub fur: Option<&'a ImageF32>,
    /// Gabor angle and its confidence (1 channel each).
    pub orientation: Option<(&'a ImageF32, &'a ImageF32)>,
    /// Where the orientation term counts (None: everywhere).
    pub region: Option<&'a ImageF32>,
}

/// The weighted image losses of [`Renderer::image_step`]: `rgb` x
/// `(1 - lambda_dssim) L1 + lambda_dssim (1 - SSIM)` on the colour
/// (unmasked), `silhouette` x mean |alpha - mask|, `fur` x mean |fur - fur
/// mask|, `orientation` x the confidence-weighted angle error in the region
/// ([`super::losses`]). A term runs when its weight is positive and the view
/// has its target.
#[derive(Debug, Clone, Copy)]
pub struct ImageLoss {
    pub lambda_dssim: f32,
    pub rgb: f32,
    pub silhouette: f32,
    pub fur: f32,
    pub orientation: f32,
}

/// Wall seconds of one image step's phases.
#[derive(Debug, Clone, Copy, Default)]
pub struct StepSeconds {
    pub render: f64,
    pub loss: f64,
    pub backward: f64,
}

/// A view's targets kept on the device between steps (uploaded once), so
/// that a step moves no image between host and device.
#[derive(Debug)]
pub enum ResidentTarget {
    #[cfg(feature = "gpu")]
    Gpu(super::gpu::GpuTarget),
}

/// Weighted loss terms by name (`rgb`, `sil`, `mask`, `ori`, in that order)
/// and the Gaussians' gradients.
pub type StepResult = (Vec<(&'static str, f32)>, GaussianGrads, StepSeconds);

impl Renderer {
    /// `t` kept on this device for [`Renderer::image_step`]: uploaded now on
    /// the GPU (checked as the losses check their inputs); None on the CPU,
    /// whose steps read the host images.
    pub fn resident_target(
        &self,
        t: &ViewTargets<'_>,
    ) -> Result<Option<ResidentTarget>, RenderError> {
        match self {
            Renderer::Cpu => {
                let _ = t;
                Ok(None)
            }
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => r.target(t).map(|g| Some(ResidentTarget::Gpu(g))),
        }
    }

    /// One learning step on a view: render `g` from `cam`, the weighted
    /// image losses `w` against `t` and their gradient, and the Gaussians'
    /// gradients. On the host path: [`Renderer::render`], the losses of
    /// [`super::losses`] in the order of [`ImageLoss`] (SSIM on this
    /// device) and [`Renderer::backward`]; with a `resident` target on the
    /// GPU the same formulas with the images kept on the device
    /// (`gpu::GpuRenderer::image_step`, feature `gpu`).
    pub fn image_step(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        t: &ViewTargets<'_>,
        resident: Option<&ResidentTarget>,
        w: &ImageLoss,
    ) -> Result<StepResult, RenderError> {
        match (self, resident) {
            #[cfg(feature = "gpu")]
            (Renderer::Gpu(r), Some(ResidentTarget::Gpu(rt))) => r.image_step(g, cam, s, rt, w),
            #[cfg(feature = "gpu")]
            (Renderer::Cpu, Some(_)) => Err(RenderError::Gpu(
                "a GPU-resident target given to the CPU renderer".into(),
            )),
            _ => self.host_image_step(g, cam, s, t, w),
        }
    }

    /// [`Renderer::image_step`] through host images.
    fn host_image_step(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        t: &ViewTargets<'_>,
        w: &ImageLoss,
    ) -> Result<StepResult, RenderError> {
        use super::losses;
        let mut secs = StepSeconds::default();
        let clock = std::time::Instant::now();
        let (out, st) = self.render(g, cam, s)?;
        secs.render = clock.elapsed().as_secs_f64();
        let clock = std::time::Instant::now();
        let scale = |mut g: ImageF32, w: f32| {
            g.data.iter_mut().for_each(|v| *v *= w);
            g
        };
        let mut terms = Vec::new();
        let mut dl = OutputGrads::default();
        if w.rgb > 0.0 {
            let (v, g) = self.l1_dssim(&out.rgb, t.rgb, None, w.lambda_dssim)?;
            terms.push(("rgb", w.rgb * v));
            dl.rgb = Some(scale(g, w.rgb));
        }
        if let (true, Some(m)) = (w.silhouette > 0.0, t.mask) {
            let (v, g) = losses::silhouette(&out.alpha, m, None)?;
            terms.push(("sil", w.silhouette * v));
            dl.alpha = Some(scale(g, w.silhouette));
        }
        if let (true, Some(f)) = (w.fur > 0.0, t.fur) {
            let (v, g) = losses::fur_mask(&out.fur, f, None)?;
            terms.push(("mask", w.fur * v));
            dl.fur = Some(scale(g, w.fur));
        }
        if let (true, Some((angle, conf))) = (w.orientation > 0.0, t.orientation) {
            let (v, g) = losses::orientation(&out.orientation, angle, conf, t.region)?;
            terms.push(("ori", w.orientation * v));
            dl.orientation = Some(scale(g, w.orientation));
        }
        secs.loss = clock.elapsed().as_secs_f64();
        let clock = std::time::Instant::now();
        let grads = self.backward(g, cam, s, &st, &dl)?;
        secs.backward = clock.elapsed().as_secs_f64();
        Ok((terms, grads, secs))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn choices_resolve_or_fail_clearly() {
        assert_eq!(Renderer::from_choice("cpu").unwrap().name(), "cpu");
        let auto = Renderer::from_choice("auto").unwrap();
        match Renderer::from_choice("gpu") {
            Ok(r) => {
                assert_eq!(r.name(), "gpu");
                assert_eq!(auto.name(), "gpu");
                assert!(r.adapter().is_some());
            }
            Err(e) => {
                assert_eq!(auto.name(), "cpu");
                assert!(e.contains("gpu") || e.contains("adapter"), "{e}");
            }
        }
        assert!(Renderer::from_choice("tpu").is_err());
        assert_eq!(Renderer::Cpu.metrics()["device"], "cpu");
    }

    #[test]
    fn unset_parameter_is_the_cpu_and_is_declared_optional() {
        let spec = device_param();
        assert!(
            spec.default.is_none() && spec.optional,
            "unset must leave keys unchanged"
        );
        assert_eq!(spec.choices, DEVICE_CHOICES);
        let unset = Params::default();
        assert_eq!(Renderer::from_params(&unset).unwrap().name(), "cpu");
        let mut p = Params::default();
        p.0.insert("device".into(), fure_stage_api::Value::Str("cpu".into()));
        assert_eq!(Renderer::from_params(&p).unwrap().name(), "cpu");
    }
}
