//! The image losses of the loop: strands to segment Gaussians, rendered with
//! the body occluders from the training views, compared with the photos,
//! masks, fur masks and Gabor orientation maps; gradients back to the points.
//!
//! Body occluders. The strands alone cannot explain the photos: behind sparse
//! fur and on non-fur parts the skin is visible, and without a body the
//! strands on the far side would show through and corrupt the silhouette and
//! orientation comparisons. We therefore render the body mesh (M_root, or
//! M_outer in the shape-prior ablation) as `body_gaussians` opaque, flat
//! surface Gaussians (area-weighted seeded samples; discs of standard deviation
//! 0.6 x the sample spacing, one tenth of that thick, fur flag off) with a
//! trainable colour each. They never move; both methods get the same ones.
//!
//! Strand appearance: one trainable RGB colour per strand (degree-0 SH), lazy
//! Adam on the sampled strands; identical for codec and dense. With
//! `sh_degree = 1` every strand also gets band-1 coefficients (a colour that
//! varies linearly with the view direction, 3DGS's first band), zero at the
//! start, trained by the same lazy Adam on every segment of the strand. The
//! default is degree 0, the scenes' need measured on the dev split: with
//! lights fixed in the world, diffuse fur looks the same from every view and
//! a narrow specular lobe is beyond band 1 (tiger +0.1 dB held-out PSNR, fox
//! a tie, F-scores identical; docs/history.md). A capture with broad
//! view-dependent sheen is what it is for. With `color_ramp` every strand's
//! colour also changes linearly from root to tip (`set_ramp`): fur darkens
//! towards the root, where the coat shadows itself, and one colour per strand
//! can only average that (rendering a synthetic scene's GT strands this way,
//! the `appearance_ceiling` example, bounds what one colour reaches). The ramp
//! is fitted with the colour, in closed form, by every colour fit and stays
//! fixed while training; the exported strands carry the middle colour. The
//! codec's default is on (dev split, at the held-out renders' pixel filter:
//! tiger +0.3 dB held-out PSNR, fox, lynx, sheepdog and the Blender fox ties,
//! every F-score a tie; docs/history.md); the dense baseline keeps it off,
//! since on its strands it tied on every dev scene. Colours start
//! from the views ([`ImageLosses::fit_colors`], `fit_colors`): every
//! strand and body occluder takes the mean of the training pixels it makes
//! (with a ramp: the weighted least-squares line through its segments' means,
//! a small ridge keeping strands seen at one segment flat),
//! weighted by its blending weight `alpha_i T_i` there, so the renderer itself
//! decides what is visible (occlusion by the body and by other strands). The
//! two sums (weighted pixels, weights) are the colour gradients of two linear
//! losses (the masked straight colour, then the mask). Why: a strand is
//! sampled only ~8 times in the codec's 100 iterations, so from one common
//! starting colour Adam leaves the coat a washed-out brown, and L_rgb then
//! pulls geometry to explain colour errors. The fit composites every strand in
//! each of its views once ([`render::blend_sums`] takes both sums in the
//! compositing pass itself rather than through a render and two backward
//! passes: a view costs about one forward render of the coat). The fit
//! before training only makes the first photometric losses meaningful and
//! renders 6 evenly spaced views (`fit_color_views_start`); the final fit,
//! whose colours are written, renders 12 (`fit_color_views`). A second fit
//! after training under the same opacity (`start_end`) gave no further gain
//! on the dev scenes. One under the
//! held-out renders' coverage (`start_held_out`), where deeper strands and the
//! body show through the thinner strands, is the codec's default: the colours
//! are fitted in the image formation they are shown in (dev split: tiger
//! +0.6 dB, fox +0.2 dB, geometry unchanged). The dense baseline keeps
//! `start`: on its strands the same second fit loses 0.5 dB on the tiger
//! (fox a tie; docs/history.md); why was not measured. Each learner declares its own `fit_colors` for that reason.
//!
//! Least-squares colours (`fit_color_refinements`, the codec's final fit).
//! The weighted means match each Gaussian to its own pixels alone; where
//! strands and the body share a pixel, the composite they make is not the
//! photo (a thin strand over the body takes the body's colour into its own,
//! and the body then adds its colour again beneath it). The codec's final
//! fit therefore takes 2 majorise-minimise steps from the means toward the
//! colours whose renders best match the fit's views (`refine_colors`: each
//! step a render and a blend-sum pass per view, the squared error never
//! grows). Dev split, 4 steps against none: held-out PSNR tiger +0.5 dB, fox
//! +0.6, lynx +0.6, sheepdog +1.0, Blender fox +1.6, every F-score a tie;
//! 2 steps tie 4 on every dev scene (the Blender fox included) at 40-45 %
//! less fit time, 1 step loses the tiger (docs/history.md). The dense
//! baseline's colours are Adam's over 1,800 iterations, which gets closer to
//! the least-squares colours by itself; it keeps no final fit.
//!
//! Held-out renders (`held_out_coverage = "width"`): strand Gaussians are
//! trained at opacity 1 on strand subsets, where a strand must show at all;
//! rendered with every strand, the renderer's screen-space low-pass (0.3 px^2)
//! makes each sub-pixel strand about a pixel wide and opaque, so the coat
//! reads too dense and its silhouette about a pixel too wide. The held-out
//! views therefore scale each segment's opacity so that its integrated
//! coverage is that of its true width ([`width_coverage`], Mip-Splatting's
//! compensation of its 2D filter, applied to the thin axis only). Both
//! learners are rendered the same way; `opaque` keeps the training opacity.
//!
//! Held-out low-pass (`held_out_low_pass`, 0.1 px^2). The 0.3 px^2 that
//! 3DGS adds to every splat keeps tiny Gaussians about a pixel wide so that
//! training reaches them; a camera's pixel integrates over its area, a box of
//! variance 1/12 px^2, which Mip-Splatting's 2D filter approximates with 0.1.
//! At 0.3 the held-out views' opaque outline (body occluders and the strands
//! over them) came out about half a pixel too wide all round: on the tiger
//! 70 % of the held-out squared error lay in the two pixel rings just
//! outside the photo's silhouette, with the GT strands drawn this way as with
//! the learned ones. The held-out renders, and the colour fit made for them,
//! therefore use 0.1; training keeps 0.3 (0.1 there tied every dev F-score;
//! docs/history.md, "The held-out views' pixel filter").
//!
//! Views: each iteration renders `views_per_iteration` distinct training
//! views drawn with a seeded generator; the losses are averaged over them.
//! Targets: the photo composited over the renderer's black background with
//! its own alpha (when it has one); the silhouette is the view's mask; the fur
//! mask is `<stem>_fur.png` (when present; else L_mask is skipped for the
//! view); the orientation target is the `orientation` input's map for the
//! view (when connected; else L_ori is skipped).

use std::path::Path;

use fure_stage_api::StageError;
use glam::{Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::model::RowAdam;
use super::train::ImageTerm;
use crate::data::camera::Camera;
use crate::data::image::ImageF32;
use crate::data::mesh::Mesh;
use crate::data::strands::Strands;
use crate::formats;
use crate::render::device::{ImageLoss, ResidentTarget, ViewTargets};
use crate::render::{self, GaussianGrads, Gaussians, RenderSettings};

/// Settings of the image losses.
#[derive(Debug, Clone)]
pub struct ImageConfig {
    pub views_per_iteration: usize,
    pub lr_color: f32,
    pub l_rgb: f32,
    pub l_sil: f32,
    pub l_ori: f32,
    pub l_mask: f32,
    pub body_gaussians: usize,
    pub seed: u64,
    /// Normalised confidence below which a pixel has no orientation target.
    pub ori_min_confidence: f32,
    /// The silhouette's share of the frame at which the colour, silhouette and fur-mask terms
    /// keep their weights ([`subject_scale`]); `None`: means over the frame.
    pub subject_share: Option<f32>,
    /// Training views the final colour fit uses, evenly spaced (0 = all).
    pub fit_color_views: usize,
    /// Training views the start colour fit uses (0 = all).
    pub fit_color_views_start: usize,
    /// Strand coverage in the held-out renders.
    pub held_out_coverage: Coverage,
    /// The renderer's screen-space low-pass (pixels^2) in the held-out renders
    /// and the colour fit made for them (training keeps the renderer's default).
    pub held_out_low_pass: f32,
    /// Where the renderer runs (the stage's `device` parameter).
    pub device: render::device::Renderer,
    /// Strand colours' spherical-harmonics degree: 0 (one RGB colour) or 1
    /// (plus a trainable linear view dependence per strand, zero at the start).
    pub sh_degree: u32,
    /// Give every strand a colour ramp from root to tip, fitted with its
    /// colour by [`ImageLosses::fit_colors`] (see `set_ramp`).
    pub color_ramp: bool,
    /// Majorise-minimise steps toward the least-squares colours after the
    /// final colour fit's weighted means (`refine_colors`).
    pub fit_color_refinements: usize,
}

/// One training view's targets.
pub struct ViewData {
    pub camera: Camera,
    /// RGB over black.
    pub rgb: ImageF32,
    pub mask: Option<ImageF32>,
    pub fur: Option<ImageF32>,
    /// Orientation angle in [0, pi) and confidence (1 channel each).
    pub orientation: Option<(ImageF32, ImageF32)>,
    /// The factor of this view's colour, silhouette and fur-mask weights ([`subject_scale`]).
    pub loss_scale: f32,
}

/// The factor of a view's colour, silhouette and fur-mask weights under `subject_share`: the
/// reference share over the share of the frame the view's `silhouette` fills (pixels above
/// 0.5), so that those terms, means over the frame, count as means over the subject, as the
/// orientation term does. The same capture framed more loosely then trains with the same
/// balance of terms. 1 without a reference, a silhouette or a pixel of the subject in it: a
/// mean over no subject pixel has no meaning (counted as one pixel, it would weigh the view
/// by the frame's whole area).
pub fn subject_scale(silhouette: Option<&ImageF32>, subject_share: Option<f32>) -> f32 {
    let (Some(m), Some(reference)) = (silhouette, subject_share) else {
        return 1.0;
    };
    match m.data.iter().filter(|&&v| v > 0.5).count() {
        0 => 1.0,
        inside => reference * m.data.len() as f32 / inside as f32,
    }
}

/// The image term.
pub struct ImageLosses {
    cfg: ImageConfig,
    views: Vec<ViewData>,
    /// Each view's targets kept on the device (GPU), else None.
    resident: Vec<Option<ResidentTarget>>,
    test_cameras: Vec<Camera>,
    body: Gaussians,
    body_adam: render::Adam,
    body_group: usize,
    widths: Vec<f32>,
    colors: Vec<[f32; 3]>,
    color_adam: RowAdam,
    /// Band-1 SH coefficients, [`BAND1`] per strand (see [`set_band1`]);
    /// empty at `sh_degree = 0`.
    sh1: Vec<f32>,
    sh1_adam: RowAdam,
    /// Colour change from root to tip per strand (see `set_ramp`); empty
    /// without `color_ramp`. Set by the colour fits, fixed while training.
    ramp: Vec<[f32; 3]>,
    /// The training renders' settings.
    settings: RenderSettings,
    /// The held-out renders' settings (their own low-pass).
    held_out_settings: RenderSettings,
    timing: ImageTiming,
}

/// Where the training iterations' image terms spent their wall time, in
/// seconds (metrics.json `image_seconds`): the renderer's forward pass, the
/// image losses, and the backward pass (the renderer's, then the chain rule
/// to the strand points). The `device` changes the first and the third.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImageTiming {
    pub render: f64,
    pub loss: f64,
    pub backward: f64,
}

/// Area-weighted seeded surface samples as flat opaque Gaussians.
pub fn body_gaussians(mesh: &Mesh, n: usize, seed: u64) -> Gaussians {
    let mut g = Gaussians::default();
    if n == 0 || mesh.triangles.is_empty() {
        return g;
    }
    let mut cum = Vec::with_capacity(mesh.triangles.len());
    let mut total = 0.0f64;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
        total += 0.5 * (b - a).cross(c - a).length() as f64;
        cum.push(total);
    }
    if total <= 0.0 {
        return g;
    }
    let spacing = (total as f32 / n as f32).sqrt();
    let scale = Vec3::new(0.6 * spacing, 0.6 * spacing, 0.06 * spacing);
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xB0D1);
    for _ in 0..n {
        let x = rng.gen::<f64>() * total;
        let ti = cum.partition_point(|&c| c < x).min(cum.len() - 1);
        let [a, b, c] = mesh.triangles[ti].map(|i| mesh.positions[i as usize]);
        let (mut u, mut v) = (rng.gen::<f32>(), rng.gen::<f32>());
        if u + v > 1.0 {
            u = 1.0 - u;
            v = 1.0 - v;
        }
        let p = a + u * (b - a) + v * (c - a);
        let nrm = (b - a).cross(c - a).try_normalize().unwrap_or(Vec3::Z);
        g.push(
            p,
            scale,
            Quat::from_rotation_arc(Vec3::Z, nrm),
            1.0,
            Vec3::splat(0.3),
            false,
        );
    }
    g
}

/// The first `n` Gaussians' gradients.
fn head(g: &GaussianGrads, n: usize) -> GaussianGrads {
    let mut h = g.clone();
    h.means.truncate(n);
    h.scales.truncate(n);
    h.rotations.truncate(n);
    h.opacities.truncate(n);
    h.sh.truncate(n);
    h.cov3d.truncate(n);
    h
}

impl ImageLosses {
    pub fn new(
        views_dir: &Path,
        orientation: Option<&Path>,
        body_mesh: &Mesh,
        widths: Vec<f32>,
        cfg: &ImageConfig,
    ) -> Result<Self, StageError> {
        let cams = formats::cameras::read_views(views_dir)?;
        if cams.train.is_empty() {
            return Err(StageError::input(
                "views",
                views_dir,
                "no training views in transforms.json",
            ));
        }
        let mut views = Vec::with_capacity(cams.train.len());
        for (vi, cam) in cams.train.iter().enumerate() {
            // Any photo format the views may hold (PNG, JPEG, EXR), its mask as every stage
            // finds it. The colour target is the photo over black, as the renderer draws it:
            // premultiplied by the photo's alpha, or by the mask for a photo without one (a
            // real photo's background is not the renderer's, and no strand can match it).
            let formats::cameras::ViewImages {
                mut rgb,
                mask,
                alpha,
            } = formats::cameras::read_view(views_dir, cam)?;
            if let Some(a) = alpha.as_ref().or(mask.as_ref()) {
                for (px, a) in rgb.data.chunks_exact_mut(3).zip(&a.data) {
                    for c in px {
                        *c *= a;
                    }
                }
            }
            let fpath = views_dir.join(formats::cameras::fur_mask_file_path(&cam.file_path));
            let fur = if fpath.is_file() {
                Some(formats::images::read_png(&fpath)?.first_channel())
            } else {
                None
            };
            for (what, im) in [("mask", &mask), ("fur mask", &fur)] {
                if let Some(m) = im {
                    if (m.width, m.height) != (cam.width, cam.height) {
                        return Err(StageError::input(
                            "views",
                            views_dir,
                            format!(
                                "view {vi}: {what} is {}x{}, expected {}x{}",
                                m.width, m.height, cam.width, cam.height
                            ),
                        ));
                    }
                }
            }
            let orientation = match orientation {
                Some(dir) => {
                    let (o, mut c) = read_orientation(dir, cam)?;
                    // Pixels below the confidence threshold carry no orientation target.
                    for v in c.data.iter_mut() {
                        if *v < cfg.ori_min_confidence {
                            *v = 0.0;
                        }
                    }
                    Some((o, c))
                }
                None => None,
            };
            let loss_scale = subject_scale(mask.as_ref().or(alpha.as_ref()), cfg.subject_share);
            views.push(ViewData {
                camera: cam.clone(),
                rgb,
                mask,
                fur,
                orientation,
                loss_scale,
            });
        }
        let body = body_gaussians(body_mesh, cfg.body_gaussians, cfg.seed);
        let mut body_adam = render::Adam::default();
        let body_group = body_adam.add_group("body_colour", cfg.lr_color, body.len() * 3);
        let n = widths.len();
        let resident = views
            .iter()
            .map(|v| cfg.device.resident_target(&v.targets()))
            .collect::<Result<Vec<_>, _>>()?;
        let settings = RenderSettings {
            sh_degree: cfg.sh_degree.min(1),
            ..RenderSettings::default()
        };
        Ok(ImageLosses {
            cfg: cfg.clone(),
            views,
            resident,
            test_cameras: cams.test,
            body,
            body_adam,
            body_group,
            widths,
            colors: vec![[0.5, 0.4, 0.3]; n],
            color_adam: RowAdam::new(n, 3),
            sh1: vec![0.0; if cfg.sh_degree >= 1 { n * BAND1 } else { 0 }],
            sh1_adam: RowAdam::new(if cfg.sh_degree >= 1 { n } else { 0 }, BAND1),
            ramp: if cfg.color_ramp {
                vec![[0.0; 3]; n]
            } else {
                Vec::new()
            },
            held_out_settings: RenderSettings {
                low_pass: cfg.held_out_low_pass,
                ..settings.clone()
            },
            settings,
            timing: ImageTiming::default(),
        })
    }

    /// Sets every strand's colour and every body occluder's colour to the
    /// blending-weighted mean of the training pixels it makes (see the module
    /// doc): all `points` (every strand, `l` points each) are rendered with
    /// the body in each training view; one compositing pass
    /// ([`render::blend_sums`]) gives, per Gaussian, `sum_p w(p) target(p)` and
    /// `sum_p w(p)` over the pixels inside the view's mask. Strands or occluders no view shows keep their colour.
    /// `formation` is the image formation the colours are for: the training
    /// renders', or the held-out renders' (their coverage, under which more of
    /// the layers beneath, deeper strands and the body, shows through, and
    /// their low-pass).
    /// Returns the fraction of strands that got a colour.
    pub fn fit_colors(
        &mut self,
        points: &[Vec3],
        l: usize,
        formation: Formation,
        pass: ColorFitPass,
    ) -> Result<f32, StageError> {
        let n = self.colors.len();
        if n == 0 || l < 2 || points.len() != n * l {
            return Ok(0.0);
        }
        let views = self.fit_views(pass);
        // The blending weights do not depend on the colours.
        let grey = vec![[0.5f32; 3]; n];
        let (g, segs) = self.scene(points, l, &self.widths, &grey, None, None)?;
        let sums = self.color_sums(&g, segs, l, formation, &views, |view, _| {
            let (w, h) = (view.camera.width, view.camera.height);
            let mut target = ImageF32::new(w, h, 3);
            let mut weight = ImageF32::new(w, h, 1);
            for p in 0..(w * h) as usize {
                let a = view.mask.as_ref().map_or(1.0, |m| m.data[p]);
                if a < 0.5 {
                    continue;
                }
                for k in 0..3 {
                    target.data[3 * p + k] = (view.rgb.data[3 * p + k] / a).clamp(0.0, 1.0);
                }
                weight.data[p] = 1.0;
            }
            Ok((target, weight))
        })?;
        let mean = |a: &[f64; 4]| -> Option<[f32; 3]> {
            (a[3] > MIN_COLOR_WEIGHT)
                .then(|| [0, 1, 2].map(|k| ((a[k] / a[3]) as f32).clamp(0.0, 1.0)))
        };
        let mut coloured = 0usize;
        for (c, a) in self.colors.iter_mut().zip(&sums.strands) {
            if let Some(m) = mean(a) {
                *c = m;
                coloured += 1;
            }
        }
        for ((c, r), a) in self.colors.iter_mut().zip(&mut self.ramp).zip(&sums.ramps) {
            if a.weight > MIN_COLOR_WEIGHT {
                (*c, *r) = a.solve();
            }
        }
        for (sh, a) in self.body.sh.iter_mut().zip(&sums.body) {
            if let Some(m) = mean(a) {
                sh[0] = render::gaussians::rgb_to_sh0(Vec3::from_array(m));
            }
        }
        if pass == ColorFitPass::Final {
            for _ in 0..self.cfg.fit_color_refinements {
                self.refine_colors(points, l, formation, &views)?;
            }
        }
        fure_stage_api::ensure_finite(
            "fitted strand colours",
            self.colors.iter().chain(&self.ramp).flat_map(|c| *c),
        )?;
        Ok(coloured as f32 / n as f32)
    }

    /// One majorise-minimise step of every strand's and body occluder's colour
    /// toward the colours that best reproduce the fit's views in `formation`
    /// (least squares over every pixel of the render over black against the
    /// photo). The weighted means of [`Self::fit_colors`] match each Gaussian
    /// to its pixels alone; where strands and the body share a pixel the
    /// composite they make is not the photo. With `A` the blending weights
    /// (pixels x Gaussians, each pixel's row summing to at most 1),
    /// Cauchy-Schwarz gives `A^T A <= D = diag(column sums of A)`, so the
    /// step `c += D^-1 A^T (photo - A c)` minimises a quadratic that lies
    /// above the squared error and touches it at `c`: the error never grows,
    /// and clamping to [0, 1] keeps that (D is diagonal). `D^-1 A^T r` is a
    /// blend-sum pass with the residual as its target: a step costs a render
    /// and a compositing pass per view. With ramps, each strand's step is the
    /// weighted least-squares line through its segments' residual means (a
    /// 2 x 2 block per strand and channel, so cutting the ramp at [0, 1] is
    /// not that block's exact constrained minimum; the unit test checks the
    /// error still falls at every step with ramps).
    fn refine_colors(
        &mut self,
        points: &[Vec3],
        l: usize,
        formation: Formation,
        views: &[usize],
    ) -> Result<(), StageError> {
        let n = self.colors.len();
        let sh1 = (self.sh1.len() == n * BAND1).then_some(self.sh1.as_slice());
        let ramp = (self.ramp.len() == n).then_some(self.ramp.as_slice());
        let (g, segs) = self.scene(points, l, &self.widths, &self.colors, sh1, ramp)?;
        let (_, settings) = self.formation(formation);
        let device = &self.cfg.device;
        let sums = self.color_sums(&g, segs, l, formation, views, |view, g| {
            let (out, _) = device.render(g, &view.camera, &settings)?;
            let (w, h) = (view.camera.width, view.camera.height);
            let mut residual = ImageF32::new(w, h, 3);
            for (r, (photo, shown)) in residual
                .data
                .iter_mut()
                .zip(view.rgb.data.iter().zip(&out.rgb.data))
            {
                *r = photo - shown;
            }
            let mut every_pixel = ImageF32::new(w, h, 1);
            every_pixel.data.fill(1.0);
            Ok((residual, every_pixel))
        })?;
        let step = |a: &[f64; 4]| -> Option<Vec3> {
            (a[3] > MIN_COLOR_WEIGHT).then(|| {
                Vec3::new(
                    (a[0] / a[3]) as f32,
                    (a[1] / a[3]) as f32,
                    (a[2] / a[3]) as f32,
                )
            })
        };
        if self.ramp.is_empty() {
            for (c, a) in self.colors.iter_mut().zip(&sums.strands) {
                if let Some(d) = step(a) {
                    *c = (Vec3::from_array(*c) + d)
                        .clamp(Vec3::ZERO, Vec3::ONE)
                        .to_array();
                }
            }
        } else {
            for ((c, r), a) in self.colors.iter_mut().zip(&mut self.ramp).zip(&sums.ramps) {
                if a.weight > MIN_COLOR_WEIGHT {
                    let (dc, dr) = a.solve_unclamped();
                    (*c, *r) = clamp_ramp(
                        [0, 1, 2].map(|k| c[k] as f64 + dc[k]),
                        [0, 1, 2].map(|k| r[k] as f64 + dr[k]),
                    );
                }
            }
        }
        for (sh, a) in self.body.sh.iter_mut().zip(&sums.body) {
            if let Some(d) = step(a) {
                let shown = sh[0] * render::SH_C0 + Vec3::splat(0.5);
                sh[0] = render::gaussians::rgb_to_sh0((shown + d).clamp(Vec3::ZERO, Vec3::ONE));
            }
        }
        Ok(())
    }

    /// The training views a colour fit renders: `fit_color_views` or
    /// `fit_color_views_start` of them, evenly spaced (0 = all).
    fn fit_views(&self, pass: ColorFitPass) -> Vec<usize> {
        let nv = self.views.len();
        let used = match pass {
            ColorFitPass::Start => self.cfg.fit_color_views_start,
            ColorFitPass::Final => self.cfg.fit_color_views,
        };
        let used = if used == 0 { nv } else { used.min(nv) };
        (0..used).map(|j| j * nv / used).collect()
    }

    /// The blend sums ([`render::blend_sums`]) of `g` (`segs` strand segments,
    /// `l - 1` per strand, then the body) in `formation` over `views`, per
    /// strand, per strand with its ramp positions, and per body occluder;
    /// `target` gives a view's target and pixel weight from the view and its
    /// Gaussians under the formation's coverage.
    fn color_sums(
        &self,
        g: &Gaussians,
        segs: usize,
        l: usize,
        formation: Formation,
        views: &[usize],
        target: impl Fn(&ViewData, &Gaussians) -> Result<(ImageF32, ImageF32), StageError>,
    ) -> Result<ColorSums, StageError> {
        let (coverage, settings) = self.formation(formation);
        let n = segs / (l - 1);
        let mut sums = ColorSums {
            strands: vec![[0.0; 4]; n],
            ramps: vec![RampSums::default(); if self.ramp.is_empty() { 0 } else { n }],
            body: vec![[0.0; 4]; g.len() - segs],
        };
        let add = |acc: &mut [f64; 4], v: &[f32; 4]| {
            for (a, &v) in acc.iter_mut().zip(v) {
                *a += v as f64;
            }
        };
        for view in views.iter().map(|&j| &self.views[j]) {
            let g = coverage.apply(g, segs, &view.camera, settings.low_pass);
            let (t, w) = target(view, &g)?;
            let per_gaussian = self
                .cfg
                .device
                .blend_sums(&g, &view.camera, &settings, &t, &w)?;
            for (seg, v) in per_gaussian[..segs].iter().enumerate() {
                let (s, k) = (seg / (l - 1), seg % (l - 1));
                add(&mut sums.strands[s], v);
                if let Some(r) = sums.ramps.get_mut(s) {
                    r.add(ramp_position(k, l), Vec3::new(v[0], v[1], v[2]), v[3]);
                }
            }
            for (acc, v) in sums.body.iter_mut().zip(&per_gaussian[segs..]) {
                add(acc, v);
            }
        }
        Ok(sums)
    }

    /// How `formation` covers pixels with strands, and its render settings.
    fn formation(&self, formation: Formation) -> (Coverage, RenderSettings) {
        match formation {
            Formation::Training => (Coverage::Opaque, self.settings.clone()),
            Formation::HeldOut => (self.cfg.held_out_coverage, self.held_out_settings.clone()),
        }
    }

    /// The learned strand colours (one per strand).
    pub fn colors(&self) -> &[[f32; 3]] {
        &self.colors
    }

    /// The device that renders, for the run report's note.
    pub fn device_description(&self) -> String {
        self.cfg.device.describe()
    }

    /// Where the training iterations' image terms spent their time so far.
    pub fn timing(&self) -> ImageTiming {
        self.timing
    }

    /// The device that rendered, for metrics.json.
    pub fn device_metrics(&self) -> serde_json::Value {
        self.cfg.device.metrics()
    }

    pub fn appearance_parameters(&self) -> usize {
        self.colors.len() * 3 + self.sh1.len() + self.ramp.len() * 3 + self.body.len() * 3
    }

    /// The strands (`l` points each) as segment Gaussians, then the body's;
    /// `sh1` (one row per strand) sets every segment's band-1 coefficients,
    /// `ramp` (one per strand) its colour's change from root to tip.
    fn scene(
        &self,
        points: &[Vec3],
        l: usize,
        widths: &[f32],
        colors: &[[f32; 3]],
        sh1: Option<&[f32]>,
        ramp: Option<&[[f32; 3]]>,
    ) -> Result<(Gaussians, usize), StageError> {
        let n = points.len() / l;
        let starts: Vec<u32> = (0..=n).map(|s| (s * l) as u32).collect();
        let mut g = render::strands_to_gaussians(points, &starts, widths, colors, true)?;
        let segs = g.len();
        if let Some(sh1) = sh1 {
            set_band1(&mut g.sh, sh1, l);
        }
        if let Some(ramp) = ramp {
            set_ramp(&mut g.sh, ramp, l);
        }
        g.means.extend_from_slice(&self.body.means);
        g.scales.extend_from_slice(&self.body.scales);
        g.rotations.extend_from_slice(&self.body.rotations);
        g.opacities.extend_from_slice(&self.body.opacities);
        g.sh.extend_from_slice(&self.body.sh);
        g.fur.extend_from_slice(&self.body.fur);
        Ok((g, segs))
    }

    /// Renders every held-out view of `strands` into `dir/test/NNN.png` (RGBA,
    /// straight alpha) and `dir/test/NNN.exr` (RGBA, premultiplied over black).
    pub fn render_test_views(&self, strands: &Strands, dir: &Path) -> Result<(), StageError> {
        let l = if strands.is_empty() {
            2
        } else {
            strands.strand(0).len()
        };
        let sh1 = (self.sh1.len() == strands.len() * BAND1).then_some(self.sh1.as_slice());
        let ramp = (self.ramp.len() == strands.len()).then_some(self.ramp.as_slice());
        let (g, segs) = self.scene(
            &strands.points,
            l,
            &strands.width,
            &strands.color,
            sh1,
            ramp,
        )?;
        let out_dir = dir.join("test");
        std::fs::create_dir_all(&out_dir).map_err(|e| StageError::io(&out_dir, e))?;
        for (i, cam) in self.test_cameras.iter().enumerate() {
            let (coverage, settings) = self.formation(Formation::HeldOut);
            let g = coverage.apply(&g, segs, cam, settings.low_pass);
            let (out, _) = self.cfg.device.render(&g, cam, &settings)?;
            let (w, h) = (cam.width, cam.height);
            let mut straight = ImageF32::new(w, h, 4);
            let mut pre = ImageF32::new(w, h, 4);
            for p in 0..(w * h) as usize {
                let a = out.alpha.data[p].clamp(0.0, 1.0);
                for k in 0..3 {
                    let c = out.rgb.data[3 * p + k];
                    pre.data[4 * p + k] = c;
                    straight.data[4 * p + k] = if a > 1e-6 {
                        (c / a).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                }
                pre.data[4 * p + 3] = a;
                straight.data[4 * p + 3] = a;
            }
            fure_stage_api::ensure_finite("held-out render", pre.data.iter().copied())?;
            formats::images::write_png(out_dir.join(format!("{i:03}.png")), &straight)?;
            formats::images::write_exr(out_dir.join(format!("{i:03}.exr")), &pre)?;
        }
        Ok(())
    }
}

/// Band-1 SH coefficients per strand: 3 per colour channel.
const BAND1: usize = 9;

/// Sets the band-1 SH coefficients of every strand segment Gaussian (`l - 1`
/// per strand, in strand order) from its strand's row of `sh1` ([`BAND1`]
/// per strand): row entry `3 k + b` is channel `k`'s coefficient `b`.
fn set_band1(sh: &mut [[Vec3; 4]], sh1: &[f32], l: usize) {
    if l < 2 {
        return;
    }
    for (seg, s) in sh.iter_mut().enumerate() {
        let c = &sh1[BAND1 * (seg / (l - 1))..][..BAND1];
        for b in 0..3 {
            s[1 + b] = Vec3::new(c[b], c[3 + b], c[6 + b]);
        }
    }
}

/// The adjoint of [`set_band1`]: adds `scale` times the segments' band-1
/// gradients to their strands' rows of `out` ([`BAND1`] per strand).
fn add_band1_grads(seg_grads: &[[Vec3; 4]], l: usize, scale: f32, out: &mut [f32]) {
    if l < 2 {
        return;
    }
    for (seg, g) in seg_grads.iter().enumerate() {
        let row = &mut out[BAND1 * (seg / (l - 1))..][..BAND1];
        for b in 0..3 {
            for k in 0..3 {
                row[3 * k + b] += scale * g[1 + b][k];
            }
        }
    }
}

/// Where segment `k` of a strand of `l` points sits along it, from -1/2
/// (root) to 1/2 (tip): its midpoint's arc fraction minus 1/2 (the learners'
/// points are evenly spaced along the strand).
fn ramp_position(k: usize, l: usize) -> f32 {
    (k as f32 + 0.5) / (l - 1) as f32 - 0.5
}

/// Adds every strand segment's colour offset `u r` ([`ramp_position`] `u`,
/// its strand's `ramp` row `r`) to its degree-0 SH: the strand's colour is
/// `c` at its middle and changes linearly by `r` from root to tip. Real and
/// rendered fur darken towards the root (the coat shadows itself) and change
/// hue along the hair; one colour per strand can only average that.
fn set_ramp(sh: &mut [[Vec3; 4]], ramp: &[[f32; 3]], l: usize) {
    if l < 2 {
        return;
    }
    for (seg, s) in sh.iter_mut().enumerate() {
        let u = ramp_position(seg % (l - 1), l);
        s[0] += Vec3::from(ramp[seg / (l - 1)]) * (u / render::SH_C0);
    }
}

/// Prior on a ramp, relative to the strand's total weight: a strand seen at
/// one segment keeps no ramp, one seen along its whole length (where the
/// positions' variance is about 1/12) has its fitted ramp shrunk by about 6 %.
const RAMP_RIDGE: f64 = 0.005;

/// One strand's sums for the colour fit with a ramp: the weighted least
/// squares of `c + u r` against the segments' mean pixels, over every
/// segment and view (weight `w`, weighted colour `wt`, position `u`).
#[derive(Debug, Clone, Copy, Default)]
struct RampSums {
    weight: f64,
    wu: f64,
    wuu: f64,
    wt: [f64; 3],
    uwt: [f64; 3],
}

impl RampSums {
    fn add(&mut self, u: f32, wt: Vec3, w: f32) {
        let (u, w) = (u as f64, w as f64);
        self.weight += w;
        self.wu += w * u;
        self.wuu += w * u * u;
        for k in 0..3 {
            self.wt[k] += wt[k] as f64;
            self.uwt[k] += u * wt[k] as f64;
        }
    }

    /// The colour at the strand's middle and its ramp, in [0, 1] from root
    /// to tip (the ramp is cut where an end would leave it). Needs `weight > 0`.
    fn solve(&self) -> ([f32; 3], [f32; 3]) {
        let (mid, ramp) = self.solve_unclamped();
        clamp_ramp(mid, ramp)
    }

    /// The least-squares middle colour and ramp, unbounded. Needs `weight > 0`.
    fn solve_unclamped(&self) -> ([f64; 3], [f64; 3]) {
        let (a, b) = (self.weight, self.wu);
        let c = self.wuu + RAMP_RIDGE * a;
        let det = a * c - b * b;
        let mut mid = [0.0; 3];
        let mut ramp = [0.0; 3];
        for k in 0..3 {
            let (d, e) = (self.wt[k], self.uwt[k]);
            mid[k] = (c * d - b * e) / det;
            ramp[k] = (a * e - b * d) / det;
        }
        (mid, ramp)
    }
}

/// A middle colour in [0, 1] and a ramp cut where an end of the strand would
/// leave [0, 1].
fn clamp_ramp(mid: [f64; 3], ramp: [f64; 3]) -> ([f32; 3], [f32; 3]) {
    let mut colour = [0.0f32; 3];
    let mut cut = [0.0f32; 3];
    for k in 0..3 {
        let m = mid[k].clamp(0.0, 1.0);
        let lim = 2.0 * m.min(1.0 - m);
        colour[k] = m as f32;
        cut[k] = ramp[k].clamp(-lim, lim) as f32;
    }
    (colour, cut)
}

/// A colour fit's blend sums over its views ([`ImageLosses::color_sums`]):
/// per strand, per strand with its ramp positions (empty without ramps), and
/// per body occluder, `[sum w t_r, sum w t_g, sum w t_b, sum w]`.
struct ColorSums {
    strands: Vec<[f64; 4]>,
    ramps: Vec<RampSums>,
    body: Vec<[f64; 4]>,
}

/// Below this many pixels of blending weight over all of a fit's views a
/// colour is noise: the fit keeps the previous one.
const MIN_COLOR_WEIGHT: f64 = 0.05;

/// Which colour fit runs: its number of training views differs
/// (`fit_color_views_start`, `fit_color_views`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColorFitPass {
    /// Before the first iteration: colours that make the first photometric losses meaningful.
    Start,
    /// After training: the colours the learner writes.
    Final,
}

/// The image formation a colour fit is for ([`ImageLosses::fit_colors`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Formation {
    /// The training renders': opacity 1, the training low-pass.
    Training,
    /// The held-out renders': their coverage and low-pass.
    HeldOut,
}

/// How held-out renders cover pixels with strands (see [`width_coverage`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coverage {
    /// Every strand Gaussian at its training opacity (1).
    Opaque,
    /// Opacity scaled to the strand's true width in the view.
    Width,
}

impl Coverage {
    /// `g` as this coverage renders it in `cam`: unchanged, or through [`width_coverage`].
    pub fn apply<'a>(
        self,
        g: &'a Gaussians,
        segs: usize,
        cam: &Camera,
        low_pass: f32,
    ) -> std::borrow::Cow<'a, Gaussians> {
        match self {
            Coverage::Opaque => std::borrow::Cow::Borrowed(g),
            Coverage::Width => std::borrow::Cow::Owned(width_coverage(g, segs, cam, low_pass)),
        }
    }
}

/// `g` with the opacity of each of its first `segs` Gaussians (strand
/// segments) scaled by `sqrt(v / (v + low_pass))`, `v` the squared thin
/// standard deviation in pixels at the segment's depth in `cam`: the
/// renderer's screen-space low-pass widens a sub-pixel strand to about a
/// pixel, and this keeps its integrated coverage that of its true width (the
/// long axis, many pixels, is left alone). Mip-Splatting compensates its 2D
/// filter the same way.
pub fn width_coverage(g: &Gaussians, segs: usize, cam: &Camera, low_pass: f32) -> Gaussians {
    let mut out = g.clone();
    let w2c = cam.w2c();
    for i in 0..segs.min(g.len()) {
        let depth = -w2c.transform_point3(g.means[i]).z;
        if depth <= 0.0 {
            continue;
        }
        let sigma_px = g.scales[i].y * cam.fx / depth;
        let v = sigma_px * sigma_px;
        out.opacities[i] *= (v / (v + low_pass)).sqrt();
    }
    out
}

/// Reads the orientation angle and confidence maps of a view:
/// `<image path without extension>_orient.exr` and `_conf.exr` (the
/// `orientation_maps` stage's naming). Maps computed on an image box-averaged
/// by an integer factor `f` (its `downscale`, which drops the last partial
/// rows and columns: `w / f` by `h / f`, rounded down) are upsampled by pixel
/// replication to the view's size; the pixels past the last whole block have
/// no reading and get confidence 0.
pub fn read_orientation(dir: &Path, cam: &Camera) -> Result<(ImageF32, ImageF32), StageError> {
    let stem = formats::cameras::file_stem(&cam.file_path);
    let opath = dir.join(format!("{stem}_orient.exr"));
    let o = formats::images::read_exr(&opath)?.first_channel();
    let c = formats::images::read_exr(dir.join(format!("{stem}_conf.exr")))?.first_channel();
    let (w, h) = (cam.width, cam.height);
    let factor = |m: &ImageF32| {
        (m.width > 0 && m.height > 0)
            .then(|| w / m.width)
            .filter(|f| *f >= 1 && w / f == m.width && h / f == m.height)
    };
    let f = match factor(&o) {
        Some(f) if (c.width, c.height) == (o.width, o.height) => f,
        _ => {
            return Err(StageError::input(
                "orientation",
                &opath,
                format!(
                    "maps are {}x{} (orientation) and {}x{} (confidence); the camera is \
                     {w}x{h}, expected equal sizes of the camera's divided by an integer \
                     factor (rounded down)",
                    o.width, o.height, c.width, c.height
                ),
            ))
        }
    };
    let up = |m: ImageF32, outside: f32| -> ImageF32 {
        if f == 1 {
            return m;
        }
        let mut out = ImageF32::new(w, h, 1);
        for y in 0..h {
            for x in 0..w {
                let (mx, my) = (x / f, y / f);
                out.data[(y * w + x) as usize] = if mx < m.width && my < m.height {
                    m.data[(my * m.width + mx) as usize]
                } else {
                    outside
                };
            }
        }
        out
    };
    let (o, mut c) = (up(o, 0.0), up(c, 0.0));
    normalise_confidence(&mut c);
    Ok((o, c))
}

/// Gabor confidences span many orders of magnitude (1 / (var^2 + 1e-7)); we
/// divide by the 95th percentile of the positive values and clamp to [0, 1],
/// so the orientation loss is a mean angle error in radians over confident
/// pixels, comparable across views.
pub fn normalise_confidence(c: &mut ImageF32) {
    let mut pos: Vec<f32> = c
        .data
        .iter()
        .copied()
        .filter(|v| *v > 0.0 && v.is_finite())
        .collect();
    if pos.is_empty() {
        c.data.iter_mut().for_each(|v| *v = 0.0);
        return;
    }
    let k = ((pos.len() - 1) as f32 * 0.95).round() as usize;
    let (_, p95, _) = pos.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    let p95 = p95.max(1e-30);
    for v in &mut c.data {
        *v = if v.is_finite() {
            (*v / p95).clamp(0.0, 1.0)
        } else {
            0.0
        };
    }
}

impl ViewData {
    /// The view's images as the image losses' targets; the orientation
    /// counts inside the GT fur mask (the silhouette mask when there is no
    /// fur mask).
    fn targets(&self) -> ViewTargets<'_> {
        ViewTargets {
            rgb: &self.rgb,
            mask: self.mask.as_ref(),
            fur: self.fur.as_ref(),
            orientation: self.orientation.as_ref().map(|(a, c)| (a, c)),
            region: self.fur.as_ref().or(self.mask.as_ref()),
        }
    }
}

impl ImageConfig {
    /// The weighted loss terms of one rendered view (`render::device`):
    /// L_rgb = 0.8 L1 + 0.2 (1 - SSIM) over the whole image (3DGS's
    /// photometric loss; the targets are composited over the same black
    /// background); L_sil = mean |alpha - mask|; L_mask = mean |fur - fur
    /// mask|; L_ori = the pi-periodic angle difference weighted by the
    /// normalised Gabor confidence (see [`ViewData::targets`] for where).
    /// `scale` multiplies the colour, silhouette and fur-mask weights (a view's
    /// [`subject_scale`]).
    fn image_loss(&self, scale: f32) -> ImageLoss {
        ImageLoss {
            lambda_dssim: 0.2,
            rgb: self.l_rgb * scale,
            silhouette: self.l_sil * scale,
            fur: self.l_mask * scale,
            orientation: self.l_ori,
        }
    }
}

impl ImageTerm for ImageLosses {
    fn eval(
        &mut self,
        iteration: usize,
        points: &[Vec3],
        l: usize,
        subset: &[u32],
        grad: &mut [Vec3],
    ) -> Result<Vec<(&'static str, f32)>, StageError> {
        let widths: Vec<f32> = subset.iter().map(|&i| self.widths[i as usize]).collect();
        let colors: Vec<[f32; 3]> = subset.iter().map(|&i| self.colors[i as usize]).collect();
        let sh1: Vec<f32> = if self.sh1.is_empty() {
            Vec::new()
        } else {
            subset
                .iter()
                .flat_map(|&i| &self.sh1[BAND1 * i as usize..][..BAND1])
                .copied()
                .collect()
        };
        let ramp: Vec<[f32; 3]> = subset
            .iter()
            .filter_map(|&i| self.ramp.get(i as usize).copied())
            .collect();
        let (g, segs) = self.scene(
            points,
            l,
            &widths,
            &colors,
            (!sh1.is_empty()).then_some(sh1.as_slice()),
            (!ramp.is_empty()).then_some(ramp.as_slice()),
        )?;
        let nv = self.cfg.views_per_iteration.min(self.views.len()).max(1);
        let mut rng = ChaCha8Rng::seed_from_u64(self.cfg.seed ^ 0x1A6E ^ (iteration as u64) << 20);
        let mut vids: Vec<usize> =
            rand::seq::index::sample(&mut rng, self.views.len(), nv).into_vec();
        vids.sort_unstable();
        let inv = 1.0 / nv as f32;
        let mut terms: Vec<(&'static str, f32)> = Vec::new();
        let mut gcol = vec![0.0f32; subset.len() * 3];
        let mut gsh1 = vec![0.0f32; sh1.len()];
        let mut gbody = vec![0.0f32; self.body.len() * 3];
        let starts: Vec<u32> = (0..=subset.len()).map(|s| (s * l) as u32).collect();
        for &vi in &vids {
            let view = &self.views[vi];
            let (t, gg, secs) = self.cfg.device.image_step(
                &g,
                &view.camera,
                &self.settings,
                &view.targets(),
                self.resident[vi].as_ref(),
                &self.cfg.image_loss(view.loss_scale),
            )?;
            self.timing.render += secs.render;
            self.timing.loss += secs.loss;
            let lap = std::time::Instant::now();
            for (name, v) in t {
                match terms.iter_mut().find(|x| x.0 == name) {
                    Some(x) => x.1 += inv * v,
                    None => terms.push((name, inv * v)),
                }
            }
            let sg = render::strands_backward(points, &starts, &widths, &head(&gg, segs))?;
            self.timing.backward += secs.backward + lap.elapsed().as_secs_f64();
            for (a, b) in grad.iter_mut().zip(&sg.points) {
                *a += inv * *b;
            }
            for (s, c) in sg.colors.iter().enumerate() {
                for k in 0..3 {
                    gcol[3 * s + k] += inv * c[k];
                }
            }
            for (b, sh) in gg.sh[segs..].iter().enumerate() {
                for k in 0..3 {
                    gbody[3 * b + k] += inv * sh[0][k];
                }
            }
            if !gsh1.is_empty() {
                add_band1_grads(&gg.sh[..segs], l, inv, &mut gsh1);
            }
        }
        // Appearance steps (colours stay in [0, 1]).
        let mut flat: Vec<f32> = self.colors.iter().flat_map(|c| *c).collect();
        self.color_adam
            .step(&mut flat, &gcol, subset, self.cfg.lr_color);
        for (c, f) in self.colors.iter_mut().zip(flat.chunks_exact(3)) {
            *c = [
                f[0].clamp(0.0, 1.0),
                f[1].clamp(0.0, 1.0),
                f[2].clamp(0.0, 1.0),
            ];
        }
        if !gsh1.is_empty() {
            self.sh1_adam
                .step(&mut self.sh1, &gsh1, subset, self.cfg.lr_color);
        }
        if !self.body.is_empty() {
            let mut sh: Vec<f32> = self.body.sh.iter().flat_map(|s| s[0].to_array()).collect();
            self.body_adam.step(self.body_group, &mut sh, &gbody)?;
            for (s, f) in self.body.sh.iter_mut().zip(sh.chunks_exact(3)) {
                s[0] = Vec3::new(f[0], f[1], f[2]);
            }
        }
        Ok(terms)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_of_a_view_the_factor_does_not_divide_cover_its_whole_blocks() {
        let dir = tempfile::tempdir().unwrap();
        // A 67 x 65 view filtered at a downscale of 2: the orientation stage drops the last
        // column and row, so its maps are 33 x 32.
        let cam = Camera {
            width: 67,
            height: 65,
            ..camera()
        };
        let (mut o, mut c) = (ImageF32::new(33, 32, 1), ImageF32::new(33, 32, 1));
        for (i, v) in o.data.iter_mut().enumerate() {
            *v = (i % 7) as f32 * 0.1;
        }
        c.data.iter_mut().for_each(|v| *v = 2.0);
        formats::images::write_exr(dir.path().join("c_orient.exr"), &o).unwrap();
        formats::images::write_exr(dir.path().join("c_conf.exr"), &c).unwrap();
        let (angle, conf) = read_orientation(dir.path(), &cam).unwrap();
        assert_eq!((angle.width, angle.height), (67, 65));
        // Pixel replication over the whole 2 x 2 blocks.
        for (x, y) in [(0, 0), (5, 9), (65, 63)] {
            assert_eq!(angle.pixel(x, y)[0], o.pixel(x / 2, y / 2)[0], "({x}, {y})");
            assert_eq!(conf.pixel(x, y)[0], 1.0, "({x}, {y})");
        }
        // The dropped column and row have no reading.
        assert_eq!(conf.pixel(66, 10)[0], 0.0);
        assert_eq!(conf.pixel(10, 64)[0], 0.0);
        // Maps that match no integer factor are refused, naming the sizes.
        let odd = ImageF32::new(30, 32, 1);
        formats::images::write_exr(dir.path().join("c_orient.exr"), &odd).unwrap();
        formats::images::write_exr(dir.path().join("c_conf.exr"), &odd).unwrap();
        let e = read_orientation(dir.path(), &cam).unwrap_err().to_string();
        assert!(e.contains("30x32") && e.contains("67x65"), "{e}");
    }

    /// A 64 px view of the origin from 5 units away.
    fn camera() -> Camera {
        Camera {
            file_path: "c.png".into(),
            c2w: glam::Mat4::look_at_rh(Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, Vec3::Y).inverse(),
            fx: 64.0,
            fy: 64.0,
            cx: 32.0,
            cy: 32.0,
            width: 64,
            height: 64,
        }
    }

    /// One long horizontal segment Gaussian, `sigma_px` thick in a 64 px
    /// view: the alpha summed down a column is the strand's coverage.
    fn column_coverage(sigma_px: f32, coverage: Coverage) -> f32 {
        let cam = camera();
        let thin = sigma_px * 5.0 / cam.fx;
        let mut g = Gaussians::default();
        g.push(
            Vec3::ZERO,
            Vec3::new(2.0, thin, thin),
            Quat::IDENTITY,
            1.0,
            Vec3::splat(0.5),
            true,
        );
        let settings = RenderSettings::default();
        let g = coverage.apply(&g, 1, &cam, settings.low_pass);
        let (out, _) = render::render(&g, &cam, &settings).unwrap();
        (0..64).map(|y| out.alpha.data[y * 64 + 32]).sum()
    }

    #[test]
    fn band1_strand_colours_match_finite_differences() {
        // Two 4-point strands across a 64 px view, seen off-axis so every band-1
        // coefficient changes the colour; a fixed linear loss over the image.
        let mut cam = camera();
        cam.c2w = glam::Mat4::look_at_rh(Vec3::new(2.0, 1.5, 4.5), Vec3::ZERO, Vec3::Y).inverse();
        let l = 4;
        let points: Vec<Vec3> = (0..2)
            .flat_map(|s| {
                (0..l).map(move |k| Vec3::new(-0.8 + 0.5 * k as f32, 0.3 * s as f32 - 0.15, 0.1))
            })
            .collect();
        let starts = [0u32, l as u32, 2 * l as u32];
        let widths = [0.2f32, 0.15];
        let colors = [[0.5f32, 0.4, 0.6], [0.45, 0.55, 0.5]];
        let sh1: Vec<f32> = (0..2 * BAND1)
            .map(|j| 0.05 * (j as f32 * 0.7).sin())
            .collect();
        let settings = RenderSettings {
            sh_degree: 1,
            ..RenderSettings::default()
        };
        let n_px = (cam.width * cam.height * 3) as usize;
        let w: Vec<f32> = (0..n_px)
            .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
            .collect();
        let loss = |sh1: &[f32]| -> (f64, GaussianGrads) {
            let mut g =
                render::strands_to_gaussians(&points, &starts, &widths, &colors, true).unwrap();
            set_band1(&mut g.sh, sh1, l);
            let (out, state) = render::render(&g, &cam, &settings).unwrap();
            let v = out
                .rgb
                .data
                .iter()
                .zip(&w)
                .map(|(a, b)| (a * b) as f64)
                .sum();
            let dl = render::OutputGrads {
                rgb: Some(ImageF32 {
                    width: cam.width,
                    height: cam.height,
                    channels: 3,
                    data: w.clone(),
                }),
                ..Default::default()
            };
            (
                v,
                render::backward(&g, &cam, &settings, &state, &dl).unwrap(),
            )
        };
        let (_, gg) = loss(&sh1);
        let mut analytic = vec![0.0f32; 2 * BAND1];
        add_band1_grads(&gg.sh, l, 1.0, &mut analytic);
        assert!(analytic.iter().any(|g| g.abs() > 1e-2), "{analytic:?}");
        let h = 1e-3;
        for (i, &a) in analytic.iter().enumerate() {
            let mut plus = sh1.clone();
            plus[i] += h;
            let mut minus = sh1.clone();
            minus[i] -= h;
            let fd = ((loss(&plus).0 - loss(&minus).0) / (2.0 * h as f64)) as f32;
            assert!(
                (fd - a).abs() <= 1e-3 + 1e-2 * fd.abs(),
                "entry {i}: finite difference {fd}, analytic {a}"
            );
        }
    }

    #[test]
    fn ramp_fit_recovers_a_linear_colour_along_the_strand() {
        let l = 8;
        let (mid, ramp) = ([0.5f32, 0.3, 0.6], [0.3f32, -0.2, 0.0]);
        // Every segment seen, with uneven weights: the least squares recovers the line (the
        // ridge shrinks the ramp by under 10 %).
        let mut sums = RampSums::default();
        for k in 0..l - 1 {
            let u = ramp_position(k, l);
            let w = 0.5 + (k % 3) as f32;
            let t = Vec3::from(mid) + Vec3::from(ramp) * u;
            sums.add(u, t * w, w);
        }
        let (c, r) = sums.solve();
        for k in 0..3 {
            assert!((c[k] - mid[k]).abs() < 0.02, "colour {c:?}");
            assert!(
                (r[k] - ramp[k]).abs() <= 0.1 * ramp[k].abs() + 1e-6,
                "ramp {r:?}"
            );
        }
        // One segment seen: its colour, no ramp.
        let mut one = RampSums::default();
        one.add(ramp_position(2, l), Vec3::new(0.2, 0.4, 0.8) * 3.0, 3.0);
        let (c, r) = one.solve();
        assert!(
            (Vec3::from(c) - Vec3::new(0.2, 0.4, 0.8)).length() < 1e-5,
            "{c:?}"
        );
        assert_eq!(r, [0.0; 3]);
        // A ramp that would take an end out of [0, 1] is cut at it.
        let mut steep = RampSums::default();
        for k in 0..l - 1 {
            let u = ramp_position(k, l);
            steep.add(u, Vec3::splat(0.9 + 0.8 * u), 1.0);
        }
        let (c, r) = steep.solve();
        assert!(
            c[0] + 0.5 * r[0] <= 1.0 + 1e-6 && c[0] - 0.5 * r[0] >= -1e-6,
            "{c:?} {r:?}"
        );
        // Rendered, segment k of a strand has the colour mid + u_k ramp.
        let mut sh = vec![
            [
                render::gaussians::rgb_to_sh0(Vec3::from(mid)),
                Vec3::ZERO,
                Vec3::ZERO,
                Vec3::ZERO
            ];
            l - 1
        ];
        set_ramp(&mut sh, &[ramp], l);
        for (k, s) in sh.iter().enumerate() {
            let want = Vec3::from(mid) + Vec3::from(ramp) * ramp_position(k, l);
            let got = s[0] * render::SH_C0 + Vec3::splat(0.5);
            assert!((got - want).length() < 1e-5, "segment {k}: {got} vs {want}");
        }
    }

    /// The squared error over every pixel of `views` between the held-out
    /// image formation of `points` (with `img`'s colours) and the photos.
    fn held_out_squared_error(
        img: &ImageLosses,
        points: &[Vec3],
        l: usize,
        views: &[usize],
    ) -> f64 {
        let ramp = (!img.ramp.is_empty()).then_some(img.ramp.as_slice());
        let (g, segs) = img
            .scene(points, l, &img.widths, &img.colors, None, ramp)
            .unwrap();
        let (coverage, settings) = img.formation(Formation::HeldOut);
        views
            .iter()
            .map(|&j| {
                let v = &img.views[j];
                let g = coverage.apply(&g, segs, &v.camera, settings.low_pass);
                let (out, _) = render::render(&g, &v.camera, &settings).unwrap();
                out.rgb
                    .data
                    .iter()
                    .zip(&v.rgb.data)
                    .map(|(a, b)| ((a - b) as f64).powi(2))
                    .sum::<f64>()
            })
            .sum()
    }

    #[test]
    fn colour_refinements_lower_the_fit_views_error_at_every_step() {
        let d = tempfile::tempdir().unwrap();
        let (views, body, points, l, widths) =
            crate::growth::learn::stage::tests::rough_fit_scene(d.path());
        for color_ramp in [false, true] {
            let cfg = ImageConfig {
                fit_color_views: 0,
                body_gaussians: 2000,
                ..crate::growth::learn::stage::LearnParams::defaults()
                    .unwrap()
                    .image_config(
                        crate::render::device::Renderer::Cpu,
                        crate::growth::learn::stage::OwnColors {
                            color_ramp,
                            fit_color_refinements: 0,
                        },
                    )
            };
            let mut img = ImageLosses::new(&views, None, &body, widths.clone(), &cfg).unwrap();
            img.fit_colors(&points, l, Formation::HeldOut, ColorFitPass::Final)
                .unwrap();
            let all = img.fit_views(ColorFitPass::Final);
            let mut errors = vec![held_out_squared_error(&img, &points, l, &all)];
            for _ in 0..4 {
                img.refine_colors(&points, l, Formation::HeldOut, &all)
                    .unwrap();
                errors.push(held_out_squared_error(&img, &points, l, &all));
            }
            for step in errors.windows(2) {
                assert!(
                    step[1] <= step[0] * (1.0 + 1e-6),
                    "ramp {color_ramp}: {errors:?}"
                );
            }
            assert!(errors[4] < 0.9 * errors[0], "ramp {color_ramp}: {errors:?}");
        }
    }

    /// The alpha summed along the middle row of an opaque strip `w_px` wide,
    /// tiled with flat discs as the body occluders are (standard deviation 0.6
    /// of their spacing, `spacing_px`), minus `w_px`: how much wider than the
    /// strip the renderer draws it, both edges together, at `low_pass`.
    fn strip_excess_px(w_px: f32, spacing_px: f32, low_pass: f32) -> f32 {
        let cam = camera();
        let unit = 5.0 / cam.fx;
        let h = spacing_px * unit;
        let n = (w_px / spacing_px).round() as i32;
        let mut g = Gaussians::default();
        for i in 0..n {
            for j in -40..=40 {
                let x = (i as f32 + 0.5) * h - 0.5 * w_px * unit;
                let sd = 0.6 * h;
                g.push(
                    Vec3::new(x, j as f32 * h, 0.0),
                    Vec3::new(sd, sd, 0.1 * sd),
                    Quat::IDENTITY,
                    1.0,
                    Vec3::splat(0.5),
                    false,
                );
            }
        }
        let settings = RenderSettings {
            low_pass,
            ..RenderSettings::default()
        };
        let (out, _) = render::render(&g, &cam, &settings).unwrap();
        let row: f32 = (0..64).map(|x| out.alpha.data[32 * 64 + x]).sum();
        row - w_px
    }

    /// `im` (1 channel) centred in a frame `pad` pixels wider on every side, zero outside.
    fn padded(im: &ImageF32, pad: u32) -> ImageF32 {
        let mut out = ImageF32::new(im.width + 2 * pad, im.height + 2 * pad, 1);
        for y in 0..im.height {
            for x in 0..im.width {
                let to = ((y + pad) * out.width + x + pad) as usize;
                out.data[to] = im.data[(y * im.width + x) as usize];
            }
        }
        out
    }

    #[test]
    fn a_loosely_framed_view_weighs_its_silhouette_term_as_a_tight_one() {
        // A silhouette and a render that overdraws it, framed tightly and then in a frame 16 px
        // wider on every side (11 times the area): the frame mean falls elevenfold, the
        // weighted term does not.
        let mut mask = ImageF32::new(16, 12, 1);
        let mut alpha = ImageF32::new(16, 12, 1);
        for y in 0..12u32 {
            for x in 0..16u32 {
                let i = (y * 16 + x) as usize;
                mask.data[i] = if (3..13).contains(&x) && (2..10).contains(&y) {
                    1.0
                } else {
                    0.0
                };
                alpha.data[i] = if (2..14).contains(&x) && (2..11).contains(&y) {
                    0.9
                } else {
                    0.0
                };
            }
        }
        let weighted = |alpha: &ImageF32, mask: &ImageF32, share: Option<f32>| {
            let (l, _) = crate::render::losses::silhouette(alpha, mask, None).unwrap();
            l * subject_scale(Some(mask), share)
        };
        let (tight, loose) = (
            weighted(&alpha, &mask, Some(0.2)),
            weighted(&padded(&alpha, 16), &padded(&mask, 16), Some(0.2)),
        );
        assert!(
            tight > 0.0 && (loose / tight - 1.0).abs() < 1e-5,
            "{tight} {loose}"
        );
        // Unset, the terms stay frame means (the framing weighs them).
        let (tight, loose) = (
            weighted(&alpha, &mask, None),
            weighted(&padded(&alpha, 16), &padded(&mask, 16), None),
        );
        assert!(
            (tight / loose - 2112.0 / 192.0).abs() < 1e-3,
            "{tight} {loose}"
        );
        // No silhouette, or none of the subject in it: no scale.
        assert_eq!(subject_scale(None, Some(0.2)), 1.0);
        let empty = ImageF32::new(16, 12, 1);
        assert_eq!(subject_scale(Some(&empty), Some(0.2)), 1.0);
    }

    #[test]
    fn the_held_out_low_pass_keeps_an_opaque_outline_near_its_edge() {
        // A camera pixel is a box filter: a strip 12 px wide covers 12 px of a
        // row. 3DGS's 0.3 px^2 draws it 1.6-1.9 px wider (measured), the
        // held-out renders' default about half that.
        let held_out = crate::growth::learn::stage::LearnParams::defaults()
            .unwrap()
            .image_config(crate::render::device::Renderer::Cpu, Default::default())
            .held_out_low_pass;
        for spacing in [0.5f32, 1.0] {
            let training = strip_excess_px(12.0, spacing, 0.3);
            let shown = strip_excess_px(12.0, spacing, held_out);
            assert!(training > 1.4, "spacing {spacing}: {training} px at 0.3");
            assert!(
                (0.0..1.0).contains(&shown) && shown < 0.6 * training,
                "spacing {spacing}: {shown} px held out, {training} px at 0.3"
            );
        }
    }

    #[test]
    fn width_coverage_keeps_a_thin_strands_true_coverage() {
        let root_tau = (2.0 * std::f32::consts::PI).sqrt();
        for sigma in [0.05f32, 0.1, 0.2] {
            let want = root_tau * sigma;
            let got = column_coverage(sigma, Coverage::Width);
            assert!(
                (got - want).abs() < 0.1 * want,
                "sigma {sigma}: {got} vs {want}"
            );
            // Without it the low-pass makes the strand about a pixel wide.
            let opaque = column_coverage(sigma, Coverage::Opaque);
            assert!(opaque > 2.5 * want, "sigma {sigma}: opaque {opaque}");
        }
        // A strand many pixels thick keeps (nearly) its opacity.
        let wide = width_coverage(
            &{
                let mut g = Gaussians::default();
                g.push(Vec3::ZERO, Vec3::ONE, Quat::IDENTITY, 1.0, Vec3::ONE, true);
                g
            },
            1,
            &camera(),
            0.3,
        );
        assert!(wide.opacities[0] > 0.99);
    }
}
