//! The differentiable Gaussian renderer on the GPU (feature `gpu`): WGSL
//! compute kernels through wgpu, one to one with the CPU reference
//! ([`crate::render::render`] and [`crate::render::backward`]). See
//! `docs/gpu.md` for the design, the tolerances and the determinism rule.
//!
//! Kernels (the `.wgsl` files beside this one; `common.wgsl` is prepended to
//! every one, `proj_common.wgsl` to the per-Gaussian ones and
//! `tile_common.wgsl` to the per-tile compositing ones):
//!
//! 1. `project` (per Gaussian): EWA projection with the CPU's clamps, low-pass
//!    and near cull, the support rows, and the number of 16x16 tiles the
//!    support ellipse touches (the CPU's exact per-band row intervals).
//! 2. `scan` + `scan_add`: exclusive prefix sum of the counts (integers), so
//!    Gaussian `i`'s instances own the slots `offsets[i] .. offsets[i + 1]`.
//! 3. `emit` (per Gaussian): one key `(tile, depth bits, index, slot)` per
//!    instance; `pad` fills the keys up to a power of two.
//! 4. `sort` + `sort_local` (bitonic): the keys by `(tile, depth, index)`,
//!    a total order, so every tile's list is exactly the CPU's. Steps that
//!    compare keys less than 512 apart run in workgroup memory, all of one
//!    merge in one `sort_local` dispatch; the wider ones one dispatch each.
//! 5. `ranges`: each tile's instance range.
//! 6. `forward` (a workgroup per tile, a thread per pixel, splats loaded by
//!    batches into workgroup memory): front-to-back compositing of all
//!    outputs with the CPU's alpha cut, clamp and early termination.
//! 7. `backward` (same layout, back to front): per instance, the 13
//!    screen-space gradient values summed over the tile's pixels in a fixed
//!    order in workgroup memory; then either written to the instance's slot
//!    ([`GpuMode::Deterministic`], the default) or added to the Gaussian's
//!    accumulator with a compare-exchange atomic ([`GpuMode::Atomic`]).
//! 8. `project_backward` (per Gaussian): sums its slots in tile order (as the
//!    CPU does) and applies the adjoint of the projection.
//!
//! 9. `blend` + `blend_gather` (`blend.rs`): the colour fits' per-Gaussian
//!    blend sums ([`crate::render::blend_sums`]) after a render that reads no
//!    image back: `forward`'s layout and arithmetic, each instance's four
//!    sums reduced like `backward`'s records into its slot, then per Gaussian
//!    its slots in tile order.
//!
//! Also here: the photometric loss's SSIM term ([`GpuRenderer::ssim`]:
//! `ssim_maps`, `ssim_blur` along rows then columns, `ssim_terms`, the
//! adjoints through the window again, `ssim_grad`), because at view sizes of
//! 1K pixels the CPU's SSIM costs more than the rendering; and the fused
//! image-loss step ([`GpuRenderer::image_step`]: `photo_planes`, the
//! SSIM kernels, `photo_grad`: every image loss of `render/losses.rs` the
//! learning stages use), which scores the forward image where it lies
//! against targets uploaded once per view and hands its pixel gradients to
//! `backward` on the device, because moving the images to the host and back
//! cost more than computing the losses.
//!
//! Host side: every buffer comes from a pool kept between calls (`pool.rs`,
//! whose invariant is that no kernel reads bytes its call did not write),
//! uploads go through pooled staging buffers, and readbacks are unpacked in
//! parallel straight from mapped memory: the first port allocated and copied
//! per call, and that, not the kernels, was most of its time.
//! [`GpuRenderer::set_profiling`] times each phase (the `gpu` bench prints it).

// `!(x > y)` is deliberate: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use glam::{Quat, Vec2, Vec3};
use rayon::prelude::*;
use wgpu::util::DeviceExt;

use super::device::{ImageLoss, StepResult, StepSeconds, ViewTargets};
use super::gaussians::{GaussianGrads, Gaussians};
use super::project::CamData;
use super::raster::{check_image, check_matches_state, OutputGrads, RenderOutput};
use super::{losses, RenderError, RenderSettings, TILE};
use crate::data::camera::Camera;
use crate::data::image::ImageF32;

mod blend;
mod gabor;
mod pool;
#[cfg(test)]
mod tests;

pub use gabor::GaborInput;

use pool::{Pool, Pooled};

/// How the backward pass accumulates per-tile gradients into Gaussians.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GpuMode {
    /// Per-instance records summed per Gaussian in tile order: the same bits
    /// on every run on one adapter and driver (the default; fure requires
    /// same inputs -> same bytes).
    Deterministic,
    /// Per-tile sums added to the Gaussian with atomics: no per-instance
    /// buffer and no gather pass, but the addition order, and so the last
    /// bits, vary run to run.
    Atomic,
}

/// Camera and settings as the kernels read them (`Params` in common.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    w0: [f32; 4],
    w1: [f32; 4],
    w2: [f32; 4],
    tw: [f32; 4],
    center: [f32; 4],
    bg: [f32; 4],
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

/// The SSIM kernels' uniforms (`SsimParams` in ssim_common.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct SsimParams {
    width: u32,
    height: u32,
    channels: u32,
    planes: u32,
    dir: u32,
    pad: [u32; 2],
    norm: f32,
    k: [[f32; 4]; 3],
}

/// The image-loss step's uniforms (`PhotoParams` in photo_common.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct PhotoParams {
    width: u32,
    height: u32,
    terms: u32,
    pad0: u32,
    norm: f32,
    lambda: f32,
    pix_norm: f32,
    ori_norm: f32,
    w_rgb: f32,
    w_sil: f32,
    w_fur: f32,
    w_ori: f32,
}

/// f32 per Gaussian in the input record (proj_common.wgsl).
const GREC: usize = 24;
/// f32 per Gaussian in the gradient record (project_backward.wgsl).
const OREC: usize = 32;
/// f32 per instance gradient record (backward.wgsl).
const NV: u64 = 13;
/// Bytes of a projected splat (`Splat` in common.wgsl).
const SPLAT_BYTES: u64 = 80;
/// Stride of the per-dispatch `Small` uniforms (the largest uniform offset alignment).
const SMALL_STRIDE: u64 = 256;
/// Keys per workgroup of `sort_local` (its `BLOCK`).
const SORT_BLOCK: u32 = 512;

struct Kernels {
    project: wgpu::ComputePipeline,
    scan: wgpu::ComputePipeline,
    scan_add: wgpu::ComputePipeline,
    emit: wgpu::ComputePipeline,
    pad: wgpu::ComputePipeline,
    sort: wgpu::ComputePipeline,
    sort_local: wgpu::ComputePipeline,
    ranges: wgpu::ComputePipeline,
    forward: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
    blend: wgpu::ComputePipeline,
    blend_gather: wgpu::ComputePipeline,
    project_backward: wgpu::ComputePipeline,
    ssim_maps: wgpu::ComputePipeline,
    ssim_blur: wgpu::ComputePipeline,
    ssim_terms: wgpu::ComputePipeline,
    ssim_grad: wgpu::ComputePipeline,
    photo_planes: wgpu::ComputePipeline,
    photo_grad: wgpu::ComputePipeline,
    gabor: wgpu::ComputePipeline,
}

/// A wgpu device with the renderer's kernels compiled.
pub struct GpuRenderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    kernels: Kernels,
    mode: GpuMode,
    /// Serialises submissions that share the device (one render at a time).
    lock: Mutex<()>,
    /// Wall time per phase while profiling is on ([`GpuRenderer::set_profiling`]).
    profile: Mutex<Option<GpuProfile>>,
    /// Device and staging buffers kept between calls (pool.rs).
    pool: Arc<Pool>,
    /// Host-side packing buffer reused between uploads (no page faults per call).
    scratch: Mutex<Vec<f32>>,
}

/// Wall time per phase of [`GpuRenderer::render`] and [`GpuRenderer::backward`],
/// summed over calls. While profiling, each device phase is submitted and
/// waited for on its own, so the phases add up to more than an unprofiled
/// call; the split says where the time goes, not what a call costs.
#[derive(Debug, Clone, Default)]
pub struct GpuProfile {
    /// (phase, milliseconds summed, calls), in the order first seen.
    pub phases: Vec<(&'static str, f64, u32)>,
}

impl GpuProfile {
    fn add(&mut self, phase: &'static str, ms: f64) {
        match self.phases.iter_mut().find(|p| p.0 == phase) {
            Some(p) => {
                p.1 += ms;
                p.2 += 1;
            }
            None => self.phases.push((phase, ms, 1)),
        }
    }
}

/// Lap timer over one call's phases; free when profiling is off.
struct Laps<'a> {
    r: &'a GpuRenderer,
    t: Instant,
    on: bool,
}

impl<'a> Laps<'a> {
    fn new(r: &'a GpuRenderer) -> Laps<'a> {
        let on = r.profile.lock().map(|p| p.is_some()).unwrap_or(false);
        Laps {
            r,
            t: Instant::now(),
            on,
        }
    }

    /// Ends a phase of host work.
    fn host(&mut self, phase: &'static str) {
        if self.on {
            let ms = self.t.elapsed().as_secs_f64() * 1e3;
            if let Ok(mut p) = self.r.profile.lock() {
                if let Some(p) = p.as_mut() {
                    p.add(phase, ms);
                }
            }
            self.t = Instant::now();
        }
    }

    /// Ends a phase of device work: submits what `enc` holds and waits.
    fn device(
        &mut self,
        phase: &'static str,
        enc: &mut wgpu::CommandEncoder,
    ) -> Result<(), RenderError> {
        if self.on {
            let done = std::mem::replace(enc, self.r.encoder());
            self.r.submit_wait(done)?;
            self.host(phase);
        }
        Ok(())
    }
}

impl std::fmt::Debug for GpuRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRenderer")
            .field("adapter", &self.info.name)
            .field("backend", &self.info.backend)
            .field("mode", &self.mode)
            .finish()
    }
}

/// What [`GpuRenderer::backward`] needs from [`GpuRenderer::render`]: the
/// buffers of the forward pass, kept on the device.
pub struct GpuState {
    width: u32,
    height: u32,
    n: usize,
    n_inst: u32,
    params: Params,
    gauss: Pooled,
    splats: Pooled,
    offsets: Pooled,
    keys: Pooled,
    ranges: Pooled,
    tfinal: Pooled,
    ncontrib: Pooled,
    /// The forward image, 8 f32 per pixel (read in place by [`GpuRenderer::photometric`]).
    img: Pooled,
    /// Gaussian-pixel evaluations in the forward pass.
    pub evaluations: u64,
}

impl std::fmt::Debug for GpuState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuState")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("n", &self.n)
            .field("instances", &self.n_inst)
            .finish()
    }
}

impl GpuState {
    /// Number of (tile, Gaussian) instances.
    pub fn instance_count(&self) -> usize {
        self.n_inst as usize
    }
}

fn gpu_err(m: impl std::fmt::Display) -> RenderError {
    RenderError::Gpu(m.to_string())
}

/// The adapter kinds in order of preference (a real GPU first, then the
/// software rasteriser).
fn rank(t: wgpu::DeviceType) -> u32 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    }
}

static SHARED: OnceLock<Result<Arc<GpuRenderer>, String>> = OnceLock::new();

impl GpuRenderer {
    /// The process-wide renderer on the preferred adapter (created once), or
    /// why there is none.
    pub fn shared() -> Result<Arc<GpuRenderer>, String> {
        SHARED
            .get_or_init(|| GpuRenderer::new(GpuMode::Deterministic).map(Arc::new))
            .clone()
    }

    /// A renderer on the preferred adapter: discrete, integrated, virtual,
    /// then CPU (lavapipe). `FURE_GPU_ADAPTER=substring` picks by name.
    pub fn new(mode: GpuMode) -> Result<GpuRenderer, String> {
        pollster::block_on(Self::new_async(mode))
    }

    async fn new_async(mode: GpuMode) -> Result<GpuRenderer, String> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::PRIMARY;
        desc.flags = wgpu::InstanceFlags::empty().with_env();
        let instance = wgpu::Instance::new(desc);
        let mut adapters = instance.enumerate_adapters(wgpu::Backends::PRIMARY).await;
        if let Ok(want) = std::env::var("FURE_GPU_ADAPTER") {
            let want = want.to_lowercase();
            adapters.retain(|a| a.get_info().name.to_lowercase().contains(&want));
        }
        adapters.sort_by_key(|a| rank(a.get_info().device_type));
        let adapter = adapters.into_iter().next().ok_or_else(|| {
            "no GPU adapter (wgpu found no Vulkan, Metal or DX12 device; on Debian \
             `apt-get install mesa-vulkan-drivers libvulkan1` gives the software one)"
                .to_string()
        })?;
        let info = adapter.get_info();
        // Everything the adapter offers (large buffers for 1M-Gaussian scenes).
        let limits = adapter.limits();
        if limits.max_compute_workgroup_storage_size < 16384
            || limits.max_compute_invocations_per_workgroup < 256
        {
            return Err(format!(
                "adapter {} lacks 16 KiB of workgroup memory or 256 invocations per workgroup",
                info.name
            ));
        }
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("fure render"),
                required_features: wgpu::Features::empty(),
                required_limits: limits,
                experimental_features: Default::default(),
                memory_hints: wgpu::MemoryHints::Performance,
                trace: Default::default(),
            })
            .await
            .map_err(|e| format!("adapter {}: {e}", info.name))?;
        let kernels = Kernels::new(&device);
        Ok(GpuRenderer {
            device,
            queue,
            info,
            kernels,
            mode,
            lock: Mutex::new(()),
            profile: Mutex::new(None),
            pool: Arc::default(),
            scratch: Mutex::new(Vec::new()),
        })
    }

    /// The adapter's name (e.g. "NVIDIA H100 80GB HBM3", "llvmpipe (LLVM 15.0.6, 256 bits)").
    pub fn adapter_name(&self) -> &str {
        &self.info.name
    }

    /// "name (backend, device type, driver)".
    pub fn adapter_description(&self) -> String {
        format!(
            "{} ({:?}, {:?}, {} {})",
            self.info.name,
            self.info.backend,
            self.info.device_type,
            self.info.driver,
            self.info.driver_info
        )
    }

    pub fn mode(&self) -> GpuMode {
        self.mode
    }

    /// Device buffers the renderer has created so far: a call of the same
    /// size as an earlier one creates none (they come from the pool).
    pub fn buffers_created(&self) -> u64 {
        self.pool.created()
    }

    /// Starts (emptying the record) or stops timing each phase of the calls.
    pub fn set_profiling(&self, on: bool) {
        if let Ok(mut p) = self.profile.lock() {
            *p = on.then(GpuProfile::default);
        }
    }

    /// The phases timed since profiling started (empty when it is off).
    pub fn profile(&self) -> GpuProfile {
        self.profile
            .lock()
            .ok()
            .and_then(|p| p.clone())
            .unwrap_or_default()
    }

    /// A storage buffer of at least `bytes` bytes from the pool; its
    /// contents are unspecified (clear it or write all of it before a kernel
    /// reads it).
    fn storage(&self, label: &str, bytes: u64) -> Pooled {
        self.pool.take(
            &self.device,
            &self.queue,
            label,
            wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            bytes,
        )
    }

    /// Maps a pooled staging buffer (idle once the last submission that used
    /// it has finished, so the wait is short).
    fn map(&self, buf: &wgpu::Buffer, mode: wgpu::MapMode) -> Result<(), RenderError> {
        let (tx, rx) = std::sync::mpsc::channel();
        buf.map_async(mode, .., move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(gpu_err)?;
        rx.recv()
            .map_err(gpu_err)?
            .map_err(|e| gpu_err(format!("mapping a staging buffer: {e}")))
    }

    /// A storage buffer holding `data`: the bytes go through a pooled
    /// staging buffer, copied in `enc`. Keep the returned staging buffer until
    /// `enc` has been submitted and waited for (else the pool could hand it
    /// out again before the copy ran).
    fn upload(
        &self,
        enc: &mut wgpu::CommandEncoder,
        label: &str,
        data: &[u8],
    ) -> Result<(Pooled, Pooled), RenderError> {
        let len = (data.len() as u64).next_multiple_of(4);
        let dst = self.storage(label, len);
        let staging = self.pool.take(
            &self.device,
            &self.queue,
            "upload",
            wgpu::BufferUsages::MAP_WRITE | wgpu::BufferUsages::COPY_SRC,
            len,
        );
        if len > 0 {
            self.map(&staging, wgpu::MapMode::Write)?;
            {
                let mut view = staging.get_mapped_range_mut(..len).map_err(gpu_err)?;
                let mut w = view.slice(..);
                w.slice(..data.len()).copy_from_slice(data);
            }
            staging.unmap();
            enc.copy_buffer_to_buffer(&staging, 0, &dst, 0, len);
        }
        Ok((dst, staging))
    }

    fn uniform(&self, data: &[u8]) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("uniform"),
                contents: data,
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    /// One dispatch: binding 0 is `uniform` (a whole buffer or a 16-byte
    /// slice at `offset`), bindings 1.. the storage buffers in order.
    fn dispatch(
        &self,
        enc: &mut wgpu::CommandEncoder,
        k: &wgpu::ComputePipeline,
        uniform: &wgpu::Buffer,
        offset: Option<u64>,
        bufs: &[&wgpu::Buffer],
        groups: (u32, u32),
    ) {
        if groups.0 == 0 || groups.1 == 0 {
            return;
        }
        let mut entries = vec![wgpu::BindGroupEntry {
            binding: 0,
            resource: match offset {
                None => uniform.as_entire_binding(),
                Some(o) => wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: uniform,
                    offset: o,
                    size: wgpu::BufferSize::new(16),
                }),
            },
        }];
        for (i, b) in bufs.iter().enumerate() {
            entries.push(wgpu::BindGroupEntry {
                binding: i as u32 + 1,
                resource: b.as_entire_binding(),
            });
        }
        let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &k.get_bind_group_layout(0),
            entries: &entries,
        });
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: None,
            timestamp_writes: None,
        });
        pass.set_pipeline(k);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(groups.0, groups.1, 1);
    }

    fn encoder(&self) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None })
    }

    fn submit_wait(&self, enc: wgpu::CommandEncoder) -> Result<(), RenderError> {
        self.queue.submit(Some(enc.finish()));
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(gpu_err)?;
        Ok(())
    }

    /// Copies `bytes` bytes of `src` from `offset` to the host and hands
    /// them to `f` in place (no copy into a host vector).
    fn read_with<T>(
        &self,
        src: &wgpu::Buffer,
        offset: u64,
        bytes: u64,
        f: impl FnOnce(&[u8]) -> T,
    ) -> Result<T, RenderError> {
        self.read_all(&[(src, offset, bytes)], |parts| f(parts[0]))
    }

    /// [`Self::read_with`] for several `(buffer, offset, bytes)` ranges at
    /// once: one staging buffer, one submission and one wait for all.
    fn read_all<T>(
        &self,
        parts: &[(&wgpu::Buffer, u64, u64)],
        f: impl FnOnce(&[&[u8]]) -> T,
    ) -> Result<T, RenderError> {
        // Each range's place in the staging buffer (copies need 4-byte multiples).
        let mut starts = Vec::with_capacity(parts.len());
        let mut size = 0u64;
        for &(_, _, bytes) in parts {
            starts.push(size);
            size += bytes.next_multiple_of(4);
        }
        if size == 0 {
            return Ok(f(&vec![&[][..]; parts.len()]));
        }
        let staging = self.pool.take(
            &self.device,
            &self.queue,
            "readback",
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            size,
        );
        let mut enc = self.encoder();
        for (&(src, offset, bytes), &at) in parts.iter().zip(&starts) {
            if bytes > 0 {
                enc.copy_buffer_to_buffer(src, offset, &staging, at, bytes.next_multiple_of(4));
            }
        }
        self.queue.submit(Some(enc.finish()));
        self.map(&staging, wgpu::MapMode::Read)?;
        let out = {
            let view = staging.get_mapped_range(..size).map_err(gpu_err)?;
            let slices: Vec<&[u8]> = parts
                .iter()
                .zip(&starts)
                .map(|(&(_, _, bytes), &at)| &view[at as usize..(at + bytes) as usize])
                .collect();
            f(&slices)
        };
        staging.unmap();
        Ok(out)
    }

    /// Exclusive prefix sum of `n` u32 in `data`, in place (recursive over
    /// the block totals). The block sums' buffers go to `keep` (they must
    /// outlive the submission).
    fn scan(
        &self,
        enc: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        n: u32,
        keep: &mut Vec<Pooled>,
    ) {
        let blocks = n.div_ceil(1024);
        let sums = self.storage("scan sums", blocks as u64 * 4);
        let u = self.uniform(bytemuck::cast_slice(&[n, 0u32, 0, 0]));
        self.dispatch(
            enc,
            &self.kernels.scan,
            &u,
            None,
            &[data, &sums],
            groups2(blocks),
        );
        if blocks > 1 {
            self.scan(enc, &sums, blocks, keep);
            self.dispatch(
                enc,
                &self.kernels.scan_add,
                &u,
                None,
                &[data, &sums],
                groups2(n.div_ceil(256)),
            );
        }
        keep.push(sums);
    }

    /// Renders `g` from `cam` on the GPU; the images match [`super::render`]'s
    /// within the tolerances of docs/gpu.md.
    pub fn render(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
    ) -> Result<(RenderOutput, GpuState), RenderError> {
        let (out, st) = self.render_state(g, cam, s, true)?;
        let out = out.ok_or_else(|| gpu_err("the forward image was not read back"))?;
        Ok((out, st))
    }

    /// [`GpuRenderer::render`], reading the images back only when
    /// `read_image` (the image-loss step scores them on the device).
    fn render_state(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        read_image: bool,
    ) -> Result<(Option<RenderOutput>, GpuState), RenderError> {
        s.validate()?;
        g.validate()?;
        let cd = CamData::new(cam)?;
        let n = g.len();
        if n >= (u32::MAX / 64) as usize {
            return Err(gpu_err(format!(
                "{n} Gaussians is too many for the GPU path"
            )));
        }
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let mut laps = Laps::new(self);
        let (w, h) = (cd.width, cd.height);
        let (tx, ty) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let n_tiles = (tx * ty) as u64;
        let mut params = make_params(&cd, s, n as u32, tx, ty, self.mode);
        // 1. Upload and project.
        let mut enc = self.encoder();
        let (gauss, staging) = {
            let mut packed = self.scratch.lock().unwrap_or_else(|e| e.into_inner());
            pack_gaussians(g, &mut packed);
            self.upload(&mut enc, "gaussians", bytemuck::cast_slice(&packed))?
        };
        let splats = self.storage("splats", n as u64 * SPLAT_BYTES);
        let offsets = self.storage("offsets", (n as u64 + 1) * 4);
        let u = self.uniform(bytemuck::bytes_of(&params));
        let mut keep = vec![staging];
        laps.host("render: pack and upload");
        enc.clear_buffer(&offsets, 0, None);
        self.dispatch(
            &mut enc,
            &self.kernels.project,
            &u,
            None,
            &[&gauss, &splats, &offsets],
            groups2((n as u32).div_ceil(256)),
        );
        laps.device("render: project", &mut enc)?;
        // 2. Offsets (n + 1 entries: the last is the instance count).
        self.scan(&mut enc, &offsets, n as u32 + 1, &mut keep);
        laps.device("render: scan", &mut enc)?;
        self.submit_wait(enc)?;
        drop(keep);
        let n_inst = self.read_with(&offsets, n as u64 * 4, 4, |b| {
            u32::from_le_bytes([b[0], b[1], b[2], b[3]])
        })?;
        laps.host("render: instance count readback");
        params.n_inst = n_inst;
        let u = self.uniform(bytemuck::bytes_of(&params));
        // 3. Keys, sort, tile ranges.
        let padded = n_inst.max(1).next_power_of_two();
        let keys = self.storage("keys", padded as u64 * 16);
        let ranges = self.storage("ranges", n_tiles * 8);
        let mut enc = self.encoder();
        enc.clear_buffer(&ranges, 0, None);
        self.dispatch(
            &mut enc,
            &self.kernels.emit,
            &u,
            None,
            &[&splats, &offsets, &keys],
            groups2((n as u32).div_ceil(256)),
        );
        laps.device("render: emit keys", &mut enc)?;
        if n_inst > 1 {
            // (kernel, Small uniform, workgroups): the padding, then the
            // bitonic steps; those with j < 512 run in workgroup memory.
            let global = groups2(padded.div_ceil(256));
            let mut steps: Vec<(&wgpu::ComputePipeline, [u32; 4], (u32, u32))> = vec![(
                &self.kernels.pad,
                [padded, n_inst, 0, 0],
                groups2((padded - n_inst).div_ceil(256)),
            )];
            let local_from = if padded >= SORT_BLOCK {
                steps.push((
                    &self.kernels.sort_local,
                    [padded, 0, 0, 0],
                    groups2(padded / SORT_BLOCK),
                ));
                2 * SORT_BLOCK
            } else {
                2
            };
            let mut k = local_from;
            while k <= padded {
                let mut j = k / 2;
                while j > 0 && (padded < SORT_BLOCK || j >= SORT_BLOCK) {
                    steps.push((&self.kernels.sort, [padded, k, j, 0], global));
                    j /= 2;
                }
                if padded >= SORT_BLOCK {
                    steps.push((
                        &self.kernels.sort_local,
                        [padded, k, 0, 0],
                        groups2(padded / SORT_BLOCK),
                    ));
                }
                k *= 2;
            }
            let stride = SMALL_STRIDE as usize / 4;
            let mut bytes: Vec<u32> = vec![0; steps.len() * stride];
            for (i, st) in steps.iter().enumerate() {
                bytes[i * stride..i * stride + 4].copy_from_slice(&st.1);
            }
            let su = self.uniform(bytemuck::cast_slice(&bytes));
            for (i, (kernel, _, groups)) in steps.iter().enumerate() {
                self.dispatch(
                    &mut enc,
                    kernel,
                    &su,
                    Some(i as u64 * SMALL_STRIDE),
                    &[&keys],
                    *groups,
                );
            }
        }
        laps.device("render: sort", &mut enc)?;
        self.dispatch(
            &mut enc,
            &self.kernels.ranges,
            &u,
            None,
            &[&keys, &ranges],
            groups2(n_inst.div_ceil(256)),
        );
        laps.device("render: tile ranges", &mut enc)?;
        // 4. Composite.
        let npix = w as u64 * h as u64;
        let img = self.storage("image", npix * 8 * 4);
        let tfinal = self.storage("t_final", npix * 4);
        let ncontrib = self.storage("n_contrib", npix * 4);
        let evals = self.storage("tile evaluations", n_tiles * 4);
        self.dispatch(
            &mut enc,
            &self.kernels.forward,
            &u,
            None,
            &[&splats, &keys, &ranges, &img, &tfinal, &ncontrib, &evals],
            (tx, ty),
        );
        self.submit_wait(enc)?;
        laps.host("render: forward");
        let image_part = (&*img, 0, if read_image { npix * 32 } else { 0 });
        let (evaluations, out) = self.read_all(&[(&evals, 0, n_tiles * 4), image_part], |b| {
            let evaluations = b[0]
                .chunks_exact(4)
                .map(|e| u32::from_le_bytes([e[0], e[1], e[2], e[3]]) as u64)
                .sum::<u64>();
            (evaluations, read_image.then(|| unpack_image(b[1], w, h)))
        })?;
        laps.host("render: image readback and unpack");
        let state = GpuState {
            width: w,
            height: h,
            n,
            n_inst,
            params,
            gauss,
            splats,
            offsets,
            keys,
            ranges,
            tfinal,
            ncontrib,
            img,
            evaluations,
        };
        Ok((out, state))
    }

    /// Gradients of all Gaussian parameters given dL/d(outputs), as
    /// [`super::backward`]. `g`, `cam` and `s` must be the ones `st` was
    /// rendered with (its buffers are reused; `g` is checked for its length).
    pub fn backward(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        st: &GpuState,
        dl: &OutputGrads,
    ) -> Result<GaussianGrads, RenderError> {
        check_state(g, cam, s, st)?;
        // Lock order: the device, then the scratch vector (as in `render`).
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let mut laps = Laps::new(self);
        let mut gpix = self.scratch.lock().unwrap_or_else(|e| e.into_inner());
        pack_pixel_grads(dl, st.width, st.height, &mut gpix)?;
        laps.host("backward: pack pixel gradients");
        let mut enc = self.encoder();
        let (gp, staging) =
            self.upload(&mut enc, "pixel gradients", bytemuck::cast_slice(&gpix))?;
        drop(gpix);
        laps.host("backward: upload");
        self.backward_from(enc, laps, st, &gp, staging)
    }

    /// The backward pass from pixel gradients already on the device (`gp`,
    /// 8 f32 per pixel), recorded after what `enc` holds; `keep` lives until
    /// the submission has finished. The caller holds the device lock.
    fn backward_from(
        &self,
        mut enc: wgpu::CommandEncoder,
        mut laps: Laps<'_>,
        st: &GpuState,
        gp: &wgpu::Buffer,
        keep: Pooled,
    ) -> Result<GaussianGrads, RenderError> {
        let n = st.n;
        let (tx, ty) = (st.params.tiles_x, st.params.tiles_y);
        let u = self.uniform(bytemuck::bytes_of(&st.params));
        let rec_len = match self.mode {
            GpuMode::Deterministic => st.n_inst as u64,
            GpuMode::Atomic => n as u64,
        };
        let rec = self.storage("instance gradients", rec_len * NV * 4);
        let outg = self.storage("gradients", n as u64 * OREC as u64 * 4);
        enc.clear_buffer(&rec, 0, None);
        self.dispatch(
            &mut enc,
            &self.kernels.backward,
            &u,
            None,
            &[
                &st.splats,
                &st.keys,
                &st.ranges,
                gp,
                &st.tfinal,
                &st.ncontrib,
                &rec,
            ],
            (tx, ty),
        );
        laps.device("backward: tiles", &mut enc)?;
        self.dispatch(
            &mut enc,
            &self.kernels.project_backward,
            &u,
            None,
            &[&st.gauss, &st.splats, &st.offsets, &rec, &outg],
            groups2((n as u32).div_ceil(256)),
        );
        self.submit_wait(enc)?;
        drop(keep);
        laps.host("backward: project_backward");
        let out = self.read_with(&outg, 0, n as u64 * OREC as u64 * 4, |b| unpack_grads(b, n))?;
        laps.host("backward: gradient readback and unpack");
        Ok(out)
    }
}

/// `g`, `cam` and `s` against the render state they must have made.
fn check_state(
    g: &Gaussians,
    cam: &Camera,
    s: &RenderSettings,
    st: &GpuState,
) -> Result<(), RenderError> {
    s.validate()?;
    let cd = CamData::new(cam)?;
    check_matches_state(g.len(), &cd, (st.width, st.height), st.n)
}

impl GpuRenderer {
    /// Weighted mean SSIM of `img` against `target` and its gradient w.r.t.
    /// `img`, on the GPU: [`losses::ssim`] (same checks, window, borders
    /// and weighting) computed in f32 instead of f64; the mean is summed on
    /// the host in the CPU's order. Within `docs/gpu.md`'s SSIM tolerance of
    /// the CPU's.
    pub fn ssim(
        &self,
        img: &ImageF32,
        target: &ImageF32,
        mask: Option<&ImageF32>,
    ) -> Result<(f32, ImageF32), RenderError> {
        let m = losses::ssim_weights(img, target, mask)?;
        let (w, h, ch) = (img.width, img.height, img.channels);
        let msum: f64 = m.iter().sum();
        let mut grad = ImageF32::new(w, h, ch);
        if msum <= 0.0 {
            return Ok((0.0, grad));
        }
        let (c, npix) = (ch as usize, (w * h) as usize);
        let norm = 1.0 / (msum * c as f64);
        // Planes x (c), y (c), weights (1).
        let mut src = vec![0.0f32; (2 * c + 1) * npix];
        src.par_chunks_mut(npix).enumerate().for_each(|(p, plane)| {
            for (q, v) in plane.iter_mut().enumerate() {
                *v = if p < c {
                    img.data[q * c + p]
                } else if p < 2 * c {
                    target.data[q * c + p - c]
                } else {
                    m[q] as f32
                };
            }
        });
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let mut enc = self.encoder();
        let (srcb, staging) = self.upload(&mut enc, "ssim inputs", bytemuck::cast_slice(&src))?;
        let (smap, gbuf, _keep) = self.ssim_chain(&mut enc, &srcb, w, h, ch, norm as f32);
        let plane_bytes = npix as u64 * 4;
        self.submit_wait(enc)?;
        drop(staging);
        let bytes = c as u64 * plane_bytes;
        let total = self.read_all(&[(&smap, 0, bytes), (&gbuf, 0, bytes)], |b| {
            let s = as_f32(b[0]);
            let mut total = 0.0f64;
            for cc in 0..c {
                for p in 0..npix {
                    total += m[p] * s[cc * npix + p] as f64;
                }
            }
            grad.data.copy_from_slice(&as_f32(b[1]));
            total
        })?;
        Ok(((total * norm) as f32, grad))
    }

    /// Records the SSIM kernels on the planes `srcb` (x, y per channel, then
    /// the weights; losses.rs `ssim` with `norm` = 1 / (weight sum x
    /// channels)): returns the per-pixel SSIM (planar) and the gradient of
    /// the weighted mean w.r.t. x (interleaved), and the intermediate
    /// buffers, to keep until the submission has run.
    fn ssim_chain(
        &self,
        enc: &mut wgpu::CommandEncoder,
        srcb: &wgpu::Buffer,
        w: u32,
        h: u32,
        ch: u32,
        norm: f32,
    ) -> (Pooled, Pooled, [Pooled; 4]) {
        let k64 = losses::gauss_kernel();
        let mut k = [[0.0f32; 4]; 3];
        for (j, v) in k64.iter().enumerate() {
            k[j / 4][j % 4] = *v as f32;
        }
        let params = |planes: usize, dir: u32| SsimParams {
            width: w,
            height: h,
            channels: ch,
            planes: planes as u32,
            dir,
            pad: [0; 2],
            norm,
            k,
        };
        let (c, npix) = (ch as usize, (w * h) as usize);
        let plane_bytes = npix as u64 * 4;
        let maps = self.storage("ssim maps", 5 * c as u64 * plane_bytes);
        let tmp = self.storage("ssim blur pass", 5 * c as u64 * plane_bytes);
        let blurred = self.storage("ssim blurred maps", 5 * c as u64 * plane_bytes);
        let smap = self.storage("ssim map", c as u64 * plane_bytes);
        let adj = self.storage("ssim adjoints", 3 * c as u64 * plane_bytes);
        let gbuf = self.storage("ssim gradient", c as u64 * plane_bytes);
        let u = |planes, dir| self.uniform(bytemuck::bytes_of(&params(planes, dir)));
        let (u_fwd_x, u_fwd_y, u_adj_x, u_adj_y) =
            (u(5 * c, 0), u(5 * c, 1), u(3 * c, 0), u(3 * c, 1));
        let per = |planes: usize| groups2(((planes * npix) as u32).div_ceil(256));
        let k = &self.kernels;
        self.dispatch(enc, &k.ssim_maps, &u_fwd_x, None, &[srcb, &maps], per(c));
        self.dispatch(
            enc,
            &k.ssim_blur,
            &u_fwd_x,
            None,
            &[&maps, &tmp],
            per(5 * c),
        );
        self.dispatch(
            enc,
            &k.ssim_blur,
            &u_fwd_y,
            None,
            &[&tmp, &blurred],
            per(5 * c),
        );
        self.dispatch(
            enc,
            &k.ssim_terms,
            &u_fwd_x,
            None,
            &[&blurred, srcb, &smap, &adj],
            per(c),
        );
        // The adjoints through the (self-adjoint) window; `maps` is free again.
        self.dispatch(enc, &k.ssim_blur, &u_adj_x, None, &[&adj, &tmp], per(3 * c));
        self.dispatch(
            enc,
            &k.ssim_blur,
            &u_adj_y,
            None,
            &[&tmp, &maps],
            per(3 * c),
        );
        self.dispatch(
            enc,
            &k.ssim_grad,
            &u_fwd_x,
            None,
            &[&maps, srcb, &gbuf],
            per(c),
        );
        (smap, gbuf, [maps, tmp, blurred, adj])
    }
}

/// A view's loss targets on the device for [`GpuRenderer::image_step`]
/// ([`super::device::ResidentTarget`]), uploaded once and read by every step
/// on that view.
pub struct GpuTarget {
    width: u32,
    height: u32,
    /// Planes y (3), SSIM weights (1, all 1), mask, fur mask, angle,
    /// confidence, region (zero where absent); photo_common.wgsl.
    planes: Pooled,
    /// The terms the view has (photo_common.wgsl `terms`, colour always).
    has: u32,
    /// Sum of the orientation region (losses.rs `orientation`'s `msum`).
    region_sum: f64,
}

/// Planes of a [`GpuTarget`].
const TARGET_PLANES: usize = 9;

impl std::fmt::Debug for GpuTarget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "GpuTarget({}x{}, terms {:#b})",
            self.width, self.height, self.has
        )
    }
}

impl GpuRenderer {
    /// Uploads a view's loss targets as a [`GpuTarget`]; each image is
    /// checked as the CPU's losses check it (size, channels, finite values).
    pub fn target(&self, t: &ViewTargets<'_>) -> Result<GpuTarget, RenderError> {
        let (w, h) = (t.rgb.width, t.rgb.height);
        losses::check("target", t.rgb, w, h, 3)?;
        let one = |what, img: Option<&ImageF32>| -> Result<(), RenderError> {
            match img {
                Some(i) => losses::check(what, i, w, h, 1),
                None => Ok(()),
            }
        };
        one("mask", t.mask)?;
        one("fur mask", t.fur)?;
        one("gabor angle", t.orientation.map(|o| o.0))?;
        one("confidence", t.orientation.map(|o| o.1))?;
        one("mask", t.region)?;
        let npix = (w * h) as usize;
        let region_sum = match t.region {
            Some(m) => m.data.iter().map(|&v| v as f64).sum(),
            None => npix as f64,
        };
        let mut planes = vec![0.0f32; TARGET_PLANES * npix];
        let single: [Option<&ImageF32>; 5] = [
            t.mask,
            t.fur,
            t.orientation.map(|o| o.0),
            t.orientation.map(|o| o.1),
            t.region,
        ];
        planes
            .par_chunks_mut(npix)
            .enumerate()
            .for_each(|(p, plane)| match p {
                0..=2 => plane
                    .iter_mut()
                    .enumerate()
                    .for_each(|(q, v)| *v = t.rgb.data[q * 3 + p]),
                3 => plane.fill(1.0),
                // The region defaults to everywhere; the other absent images stay 0.
                8 if t.region.is_none() => plane.fill(1.0),
                _ => {
                    if let Some(img) = single[p - 4] {
                        plane.copy_from_slice(&img.data);
                    }
                }
            });
        let has = 1
            | if t.mask.is_some() { 2 } else { 0 }
            | if t.fur.is_some() { 4 } else { 0 }
            | if t.orientation.is_some() { 8 } else { 0 };
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let mut enc = self.encoder();
        let (planes, staging) = self.upload(&mut enc, "target", bytemuck::cast_slice(&planes))?;
        self.submit_wait(enc)?;
        drop(staging);
        Ok(GpuTarget {
            width: w,
            height: h,
            planes,
            has,
            region_sum,
        })
    }

    /// Renders `g`, scores it against `target` with the weighted losses `wl`
    /// and differentiates, without the images leaving the device: the
    /// formulas of [`super::losses`] (`l1_dssim` unmasked, `silhouette`,
    /// `fur_mask`, `orientation`) fused between [`GpuRenderer::render`] and
    /// [`GpuRenderer::backward`]. Only the losses' partial sums (5 f32 per
    /// 256 pixels) and the Gaussians' gradients come back.
    pub fn image_step(
        &self,
        g: &Gaussians,
        cam: &Camera,
        s: &RenderSettings,
        target: &GpuTarget,
        wl: &ImageLoss,
    ) -> Result<StepResult, RenderError> {
        if !(0.0..=1.0).contains(&wl.lambda_dssim) {
            return Err(RenderError::Settings(format!(
                "D-SSIM weight lambda = {}, expected a value in [0, 1]",
                wl.lambda_dssim
            )));
        }
        for (what, v) in [
            ("colour", wl.rgb),
            ("silhouette", wl.silhouette),
            ("fur mask", wl.fur),
            ("orientation", wl.orientation),
        ] {
            if !v.is_finite() {
                return Err(RenderError::Settings(format!(
                    "{what} loss weight {v} is not finite"
                )));
            }
        }
        if (cam.width, cam.height) != (target.width, target.height) {
            return Err(RenderError::Camera(format!(
                "camera is {}x{} but the target is {}x{}",
                cam.width, cam.height, target.width, target.height
            )));
        }
        let terms = target.has
            & [wl.rgb, wl.silhouette, wl.fur, wl.orientation]
                .iter()
                .enumerate()
                .fold(0u32, |acc, (k, v)| acc | if *v > 0.0 { 1 << k } else { 0 });
        let mut secs = StepSeconds::default();
        let clock = Instant::now();
        let (_, st) = self.render_state(g, cam, s, false)?;
        secs.render = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let (w, h) = (st.width, st.height);
        let npix = (w * h) as usize;
        let plane_bytes = npix as u64 * 4;
        let ori_norm = if target.region_sum > 0.0 {
            (1.0 / target.region_sum) as f32
        } else {
            0.0
        };
        let params = PhotoParams {
            width: w,
            height: h,
            terms,
            pad0: 0,
            norm: (1.0 / (npix * 3) as f64) as f32,
            lambda: wl.lambda_dssim,
            pix_norm: (1.0 / npix as f64) as f32,
            ori_norm,
            w_rgb: wl.rgb,
            w_sil: wl.silhouette,
            w_fur: wl.fur,
            w_ori: wl.orientation,
        };
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let mut enc = self.encoder();
        // Planes x (rendered), then the target's.
        let srcb = self.storage(
            "image-loss planes",
            (3 + TARGET_PLANES) as u64 * plane_bytes,
        );
        let u = self.uniform(bytemuck::bytes_of(&params));
        enc.copy_buffer_to_buffer(
            &target.planes,
            0,
            &srcb,
            3 * plane_bytes,
            TARGET_PLANES as u64 * plane_bytes,
        );
        let (smap, gbuf, keep) = if terms & 1 != 0 {
            self.dispatch(
                &mut enc,
                &self.kernels.photo_planes,
                &u,
                None,
                &[&st.img, &srcb],
                groups2(((3 * npix) as u32).div_ceil(256)),
            );
            let (a, b, k) = self.ssim_chain(&mut enc, &srcb, w, h, 3, params.norm);
            (a, b, Some(k))
        } else {
            // No colour term: the kernel reads neither; any bound buffer does.
            (
                self.storage("ssim map", 4),
                self.storage("ssim gradient", 4),
                None,
            )
        };
        let groups = groups2((npix as u32).div_ceil(256));
        let gp = self.storage("pixel gradients", npix as u64 * 32);
        let partials = self.storage("loss partials", groups.0 as u64 * groups.1 as u64 * 20);
        self.dispatch(
            &mut enc,
            &self.kernels.photo_grad,
            &u,
            None,
            &[&st.img, &srcb, &smap, &gbuf, &gp, &partials],
            groups,
        );
        self.submit_wait(enc)?;
        drop(keep);
        let used = npix.div_ceil(256) as u64;
        let sums = self.read_with(&partials, 0, used * 20, |b| {
            let v = as_f32(b);
            let mut sums = [0.0f64; 5];
            for p in v.chunks_exact(5) {
                for (a, x) in sums.iter_mut().zip(p) {
                    *a += *x as f64;
                }
            }
            sums
        })?;
        // The CPU's scalars: each mean in f64, then cast, then weighted.
        let norm = 1.0 / (npix * 3) as f64;
        let pix_norm = 1.0 / npix as f64;
        let mut out = Vec::new();
        if terms & 1 != 0 {
            let l1 = (sums[0] * norm) as f32;
            let ssim = (sums[1] * norm) as f32;
            let lam = wl.lambda_dssim;
            out.push(("rgb", wl.rgb * ((1.0 - lam) * l1 + lam * (1.0 - ssim))));
        }
        if terms & 2 != 0 {
            out.push(("sil", wl.silhouette * (sums[2] * pix_norm) as f32));
        }
        if terms & 4 != 0 {
            out.push(("mask", wl.fur * (sums[3] * pix_norm) as f32));
        }
        if terms & 8 != 0 {
            let v = if target.region_sum > 0.0 {
                (sums[4] / target.region_sum) as f32
            } else {
                0.0
            };
            out.push(("ori", wl.orientation * v));
        }
        if let Some((name, _)) = out.iter().find(|t| !t.1.is_finite()) {
            return Err(gpu_err(format!(
                "the {name} loss is not finite (a rendered pixel is NaN or infinite)"
            )));
        }
        secs.loss = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let laps = Laps::new(self);
        let grads = self.backward_from(self.encoder(), laps, &st, &gp, srcb)?;
        secs.backward = clock.elapsed().as_secs_f64();
        Ok((out, grads, secs))
    }
}

/// Workgroups for `groups` linear workgroups: at most 65535 per dimension
/// (the kernels' `lin_id` assumes x = 65535 whenever y > 1).
fn groups2(groups: u32) -> (u32, u32) {
    if groups <= 65535 {
        (groups, 1)
    } else {
        (65535, groups.div_ceil(65535))
    }
}

fn make_params(
    cd: &CamData,
    s: &RenderSettings,
    n: u32,
    tx: u32,
    ty: u32,
    mode: GpuMode,
) -> Params {
    let v4 = |v: Vec3| [v.x, v.y, v.z, 0.0];
    Params {
        w0: v4(cd.w.x_axis),
        w1: v4(cd.w.y_axis),
        w2: v4(cd.w.z_axis),
        tw: v4(cd.tw),
        center: v4(cd.center),
        bg: v4(s.background),
        fx: cd.fx,
        fy: cd.fy,
        cx: cd.cx,
        cy: cd.cy,
        rx_lo: cd.rx_lim.0,
        rx_hi: cd.rx_lim.1,
        ry_lo: cd.ry_lim.0,
        ry_hi: cd.ry_lim.1,
        near: s.near,
        alpha_min: s.alpha_min,
        alpha_max: s.alpha_max,
        t_min: s.transmittance_min,
        extent: s.extent_sigmas,
        low_pass: s.low_pass,
        width: cd.width,
        height: cd.height,
        n,
        sh_degree: s.sh_degree,
        tiles_x: tx,
        tiles_y: ty,
        n_inst: 0,
        mode: match mode {
            GpuMode::Deterministic => 0,
            GpuMode::Atomic => 1,
        },
        pad0: 0,
        pad1: 0,
    }
}

/// The Gaussians as 24 f32 each (mean, scale, rotation xyzw, opacity, fur,
/// sh), into `v` (resized; its allocation is reused between calls).
fn pack_gaussians(g: &Gaussians, v: &mut Vec<f32>) {
    v.resize(g.len() * GREC, 0.0);
    v.par_chunks_mut(GREC).enumerate().for_each(|(i, r)| {
        let (m, s, q) = (g.means[i], g.scales[i], g.rotations[i]);
        r[..3].copy_from_slice(&[m.x, m.y, m.z]);
        r[3..6].copy_from_slice(&[s.x, s.y, s.z]);
        r[6..10].copy_from_slice(&[q.x, q.y, q.z, q.w]);
        r[10] = g.opacities[i];
        r[11] = if g.fur[i] { 1.0 } else { 0.0 };
        for k in 0..4 {
            let c = g.sh[i][k];
            r[12 + 3 * k..15 + 3 * k].copy_from_slice(&[c.x, c.y, c.z]);
        }
    });
}

/// The output gradients as 8 f32 per pixel (r, g, b, alpha, depth, ox, oy,
/// fur; zero where a gradient is absent), into `v`; every image is checked
/// for its size and for finite values (the first bad pixel is named).
fn pack_pixel_grads(dl: &OutputGrads, w: u32, h: u32, v: &mut Vec<f32>) -> Result<(), RenderError> {
    let npix = (w * h) as usize;
    v.clear();
    v.resize(npix * 8, 0.0);
    let chans: [(&Option<ImageF32>, &'static str, u32, usize); 5] = [
        (&dl.rgb, "rgb gradient", 3, 0),
        (&dl.alpha, "alpha gradient", 1, 3),
        (&dl.depth, "depth gradient", 1, 4),
        (&dl.orientation, "orientation gradient", 2, 5),
        (&dl.fur, "fur gradient", 1, 7),
    ];
    for (img, what, ch, f0) in chans {
        let Some(img) = img else { continue };
        check_image(what, img, w, h, ch)?;
        let ch = ch as usize;
        if let Some(q) = img.data.par_iter().position_first(|x| !x.is_finite()) {
            return Err(RenderError::NonFinite {
                what,
                index: q / ch,
            });
        }
        v.par_chunks_exact_mut(8)
            .zip(img.data.par_chunks_exact(ch))
            .for_each(|(p, x)| p[f0..f0 + ch].copy_from_slice(x));
    }
    Ok(())
}

/// `b` as f32 (in place when aligned, as mapped memory is).
fn as_f32(b: &[u8]) -> std::borrow::Cow<'_, [f32]> {
    match bytemuck::try_cast_slice(b) {
        Ok(v) => std::borrow::Cow::Borrowed(v),
        Err(_) => std::borrow::Cow::Owned(bytemuck::pod_collect_to_vec(b)),
    }
}

/// The forward kernel's 8 f32 per pixel as the CPU's output images.
fn unpack_image(b: &[u8], w: u32, h: u32) -> RenderOutput {
    let data = as_f32(b);
    let mut out = RenderOutput::zeros(w, h);
    (
        out.rgb.data.par_chunks_exact_mut(3),
        out.alpha.data.par_iter_mut(),
        out.depth.data.par_iter_mut(),
        out.orientation.data.par_chunks_exact_mut(2),
        out.fur.data.par_iter_mut(),
        data.par_chunks_exact(8),
    )
        .into_par_iter()
        .for_each(|(rgb, a, d, o, f, p)| {
            rgb.copy_from_slice(&p[0..3]);
            *a = p[3];
            *d = p[4];
            o.copy_from_slice(&p[5..7]);
            *f = p[7];
        });
    out
}

/// `project_backward`'s 32 f32 per Gaussian as [`GaussianGrads`].
fn unpack_grads(b: &[u8], n: usize) -> GaussianGrads {
    let v = as_f32(b);
    let mut out = GaussianGrads::zeros(n);
    (
        out.means.par_iter_mut(),
        out.scales.par_iter_mut(),
        out.rotations.par_iter_mut(),
        out.opacities.par_iter_mut(),
        out.sh.par_iter_mut(),
        out.cov3d.par_iter_mut(),
        out.means2d.par_iter_mut(),
        v.par_chunks_exact(OREC),
    )
        .into_par_iter()
        .for_each(|(m, sc, q, o, sh, c, m2, r)| {
            *m = Vec3::new(r[0], r[1], r[2]);
            *sc = Vec3::new(r[3], r[4], r[5]);
            *q = Quat::from_xyzw(r[6], r[7], r[8], r[9]);
            *o = r[10];
            for (k, c) in sh.iter_mut().enumerate() {
                *c = Vec3::new(r[11 + 3 * k], r[12 + 3 * k], r[13 + 3 * k]);
            }
            c.copy_from_slice(&r[23..29]);
            *m2 = Vec2::new(r[29], r[30]);
        });
    out
}

impl Kernels {
    fn new(device: &wgpu::Device) -> Kernels {
        const COMMON: &str = include_str!("common.wgsl");
        const PROJ: &str = include_str!("proj_common.wgsl");
        const SSIM: &str = include_str!("ssim_common.wgsl");
        const PHOTO: &str = include_str!("photo_common.wgsl");
        const TILE_K: &str = include_str!("tile_common.wgsl");
        let make = |name: &str, parts: &[&str]| {
            let src: String = parts.concat();
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(src.into()),
            });
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(name),
                layout: None,
                module: &module,
                entry_point: Some("main"),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        Kernels {
            project: make("project", &[COMMON, PROJ, include_str!("project.wgsl")]),
            scan: make("scan", &[COMMON, include_str!("scan.wgsl")]),
            scan_add: make("scan_add", &[COMMON, include_str!("scan_add.wgsl")]),
            emit: make("emit", &[COMMON, PROJ, include_str!("emit.wgsl")]),
            pad: make("pad", &[COMMON, include_str!("pad.wgsl")]),
            sort: make("sort", &[COMMON, include_str!("sort.wgsl")]),
            sort_local: make("sort_local", &[COMMON, include_str!("sort_local.wgsl")]),
            ranges: make("ranges", &[COMMON, include_str!("ranges.wgsl")]),
            forward: make("forward", &[COMMON, TILE_K, include_str!("forward.wgsl")]),
            backward: make("backward", &[COMMON, TILE_K, include_str!("backward.wgsl")]),
            blend: make("blend", &[COMMON, TILE_K, include_str!("blend.wgsl")]),
            blend_gather: make("blend_gather", &[COMMON, include_str!("blend_gather.wgsl")]),
            project_backward: make(
                "project_backward",
                &[COMMON, PROJ, include_str!("project_backward.wgsl")],
            ),
            ssim_maps: make("ssim_maps", &[COMMON, SSIM, include_str!("ssim_maps.wgsl")]),
            ssim_blur: make("ssim_blur", &[COMMON, SSIM, include_str!("ssim_blur.wgsl")]),
            ssim_terms: make(
                "ssim_terms",
                &[COMMON, SSIM, include_str!("ssim_terms.wgsl")],
            ),
            ssim_grad: make("ssim_grad", &[COMMON, SSIM, include_str!("ssim_grad.wgsl")]),
            photo_planes: make(
                "photo_planes",
                &[COMMON, PHOTO, include_str!("photo_planes.wgsl")],
            ),
            photo_grad: make(
                "photo_grad",
                &[COMMON, PHOTO, include_str!("photo_grad.wgsl")],
            ),
            gabor: make("gabor", &[COMMON, include_str!("gabor.wgsl")]),
        }
    }
}
