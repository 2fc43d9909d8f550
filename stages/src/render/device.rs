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

/// A training view's targets for [`Renderer::photometric_step`]: the
/// images themselves on the CPU; on the GPU uploaded once, so that a step
/// moves no image between host and device.
#[derive(Debug)]
pub enum PhotometricTarget<'a> {
    Cpu {
        rgb: &'a ImageF32,
        mask: &'a ImageF32,
    },
    #[cfg(feature = "gpu")]
    Gpu(super::gpu::GpuTarget),
}

/// The fitting loss of [`Renderer::photometric_step`]: `(1 - lambda_dssim)
/// L1 + lambda_dssim (1 - SSIM)` on the colour (unmasked) plus
/// `silhouette_weight` x the mean |alpha - mask|.
#[derive(Debug, Clone, Copy)]
pub struct PhotometricLoss {
    pub lambda_dssim: f32,
    pub silhouette_weight: f32,
}

/// Wall seconds of one photometric step's phases.
#[derive(Debug, Clone, Copy, Default)]
pub struct StepSeconds {
    pub render: f64,
    pub loss: f64,
    pub backward: f64,
}

impl Renderer {
    /// A view's colour (3 channels) and silhouette mask as this device's
    /// [`PhotometricTarget`] (uploaded now on the GPU).
    pub fn photometric_target<'a>(
        &self,
        rgb: &'a ImageF32,
        mask: &'a ImageF32,
    ) -> Result<PhotometricTarget<'a>, RenderError> {
        match self {
            Renderer::Cpu => Ok(PhotometricTarget::Cpu { rgb, mask }),
            #[cfg(feature = "gpu")]
            Renderer::Gpu(r) => r.target(rgb, mask).map(PhotometricTarget::Gpu),
        }
    }

    /// One fitting step on a view: render `g` from `cam`, the loss `l`
    /// against `target` and its gradient, and the Gaussians' gradients.
    /// On the CPU: [`super::render`], [`super::losses::l1_dssim`],
    /// [`super::losses::silhouette`] and [`super::backward`] in turn; on the
    /// GPU the same formulas with the images kept on the device
    /// ([`super::gpu::GpuRenderer::photometric_step`]).
    pub fn photometric_step(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        target: &PhotometricTarget<'_>,
        l: &PhotometricLoss,
    ) -> Result<(f32, GaussianGrads, StepSeconds), RenderError> {
        match target {
            PhotometricTarget::Cpu { rgb, mask } => {
                let mut secs = StepSeconds::default();
                let t = std::time::Instant::now();
                let (out, st) = self.render(g, cam, s)?;
                secs.render = t.elapsed().as_secs_f64();
                let t = std::time::Instant::now();
                let (l_rgb, g_rgb) = self.l1_dssim(&out.rgb, rgb, None, l.lambda_dssim)?;
                let (l_sil, mut g_sil) = super::losses::silhouette(&out.alpha, mask, None)?;
                for x in &mut g_sil.data {
                    *x *= l.silhouette_weight;
                }
                let loss = l_rgb + l.silhouette_weight * l_sil;
                let dl = OutputGrads {
                    rgb: Some(g_rgb),
                    alpha: Some(g_sil),
                    ..Default::default()
                };
                secs.loss = t.elapsed().as_secs_f64();
                let t = std::time::Instant::now();
                let grads = self.backward(g, cam, s, &st, &dl)?;
                secs.backward = t.elapsed().as_secs_f64();
                Ok((loss, grads, secs))
            }
            #[cfg(feature = "gpu")]
            PhotometricTarget::Gpu(t) => match self {
                Renderer::Gpu(r) => {
                    r.photometric_step(g, cam, s, t, l.lambda_dssim, l.silhouette_weight)
                }
                Renderer::Cpu => Err(RenderError::Gpu(
                    "a GPU target given to the CPU renderer".into(),
                )),
            },
        }
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
