//! What the diagnostics examples share.

use std::error::Error;
use std::process::ExitCode;

/// The exit code of an example's `run`, printing its error on stderr.
pub fn exit_code(result: Result<(), Box<dyn Error>>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// An example's error type.
pub type Res<T> = Result<T, Box<dyn Error>>;

// Not every example reads an output directory.
#[allow(dead_code)]
/// The command line of an example that reads a pipeline's output directory: that directory
/// (the first argument) and the arguments after it; `usage` when it is missing.
pub fn out_dir_and_args(usage: &str) -> Res<(std::path::PathBuf, Vec<String>)> {
    let mut args = std::env::args().skip(1);
    let dir = args.next().ok_or_else(|| format!("usage: {usage}"))?;
    Ok((dir.into(), args.collect()))
}

/// A synthetic-scene run read through `orientation`: its roots, labelled M_outer, training
/// cameras with their Gabor maps, and the GT strands.
// Not every example reads one.
#[allow(dead_code)]
pub struct OrientationRun {
    pub roots: fure_stages::data::rootset::Roots,
    pub outer: fure_stages::data::mesh::Mesh,
    pub cameras: Vec<fure_stages::data::camera::Camera>,
    pub maps: Vec<(
        fure_stages::data::image::ImageF32,
        fure_stages::data::image::ImageF32,
    )>,
    pub gt: fure_stages::data::strands::Strands,
}

#[allow(dead_code)]
impl OrientationRun {
    pub fn load(dir: &std::path::Path) -> Res<Self> {
        use fure_stages::formats;
        let cameras = formats::cameras::read_views(dir.join("scene/views"))?.train;
        let maps = cameras
            .iter()
            .map(|c| {
                fure_stages::growth::learn::image::read_orientation(
                    &dir.join("orientation/maps"),
                    c,
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(OrientationRun {
            roots: formats::json::read_json(dir.join("roots/roots.json"))?,
            outer: formats::obj::read_obj(dir.join("parts/mesh.obj"))?,
            cameras,
            maps,
            gt: formats::hair::read_hair(dir.join("scene/strands.hair"))?,
        })
    }
}

/// Where held-out renders differ from the photos along the outline: the share of the squared
/// error (renders and photos over black) in the two pixel rings just outside each photo's
/// outline (`alpha > 0.5`, 4-neighbour rings), the share of pixels those rings are, and the mean
/// coverage of render and photo in the first ring. A renderer that draws outlines too wide puts
/// much of its error there (docs/history.md, "The held-out views' pixel filter").
#[allow(dead_code)]
pub struct OutlineError {
    pub error_share: f64,
    pub pixel_share: f64,
    pub render_alpha: f64,
    pub photo_alpha: f64,
}

#[allow(dead_code)]
impl OutlineError {
    /// `renders`: a learner's `renders` folder (or its `test/`), one PNG per held-out view of `views`.
    pub fn measure(renders: &std::path::Path, views: &std::path::Path) -> Res<Self> {
        use fure_stages::formats;
        let dir = if renders.join("test").is_dir() {
            renders.join("test")
        } else {
            renders.to_path_buf()
        };
        let cams = formats::cameras::read_views(views)?.test;
        let (mut err_ring, mut err_all, mut ring_px, mut all_px) = (0.0f64, 0.0f64, 0usize, 0usize);
        let (mut render_a, mut photo_a, mut first_px) = (0.0f64, 0.0f64, 0usize);
        for (i, cam) in cams.iter().enumerate() {
            let r = formats::images::read_png(dir.join(format!("{i:03}.png")))?;
            let p = formats::cameras::read_view(views, cam)?;
            let (w, h) = (cam.width as usize, cam.height as usize);
            if (r.width as usize, r.height as usize, r.channels) != (w, h, 4u32) {
                return Err(format!("{}: expected a {w}x{h} RGBA render", dir.display()).into());
            }
            let pa = |k: usize| {
                p.alpha
                    .as_ref()
                    .or(p.mask.as_ref())
                    .map_or(1.0, |m| m.data[k])
            };
            let inside: Vec<bool> = (0..w * h).map(|k| pa(k) > 0.5).collect();
            let touches = |k: usize, set: &dyn Fn(usize) -> bool| {
                let (x, y) = (k % w, k / w);
                (x > 0 && set(k - 1))
                    || (x + 1 < w && set(k + 1))
                    || (y > 0 && set(k - w))
                    || (y + 1 < h && set(k + w))
            };
            let ring1: Vec<bool> = (0..w * h)
                .map(|k| !inside[k] && touches(k, &|j| inside[j]))
                .collect();
            for k in 0..w * h {
                let first = ring1[k];
                let second = !inside[k] && !first && touches(k, &|j| ring1[j]);
                let ra = r.data[4 * k + 3] as f64;
                let se: f64 = (0..3)
                    .map(|c| {
                        let rc = r.data[4 * k + c] as f64 * ra;
                        let pc = p.rgb.data[3 * k + c] as f64 * pa(k) as f64;
                        (rc - pc) * (rc - pc)
                    })
                    .sum();
                err_all += se;
                all_px += 1;
                if first || second {
                    err_ring += se;
                    ring_px += 1;
                }
                if first {
                    render_a += ra;
                    photo_a += pa(k) as f64;
                    first_px += 1;
                }
            }
        }
        let first = first_px.max(1) as f64;
        Ok(OutlineError {
            error_share: err_ring / err_all.max(f64::MIN_POSITIVE),
            pixel_share: ring_px as f64 / all_px.max(1) as f64,
            render_alpha: render_a / first,
            photo_alpha: photo_a / first,
        })
    }

    /// One line for the examples' output.
    pub fn describe(&self) -> String {
        format!(
            "{:.0} % of the squared error in the two pixel rings outside the photos' outline \
             ({:.1} % of the pixels); first ring's alpha: render {:.2}, photo {:.2}",
            100.0 * self.error_share,
            100.0 * self.pixel_share,
            self.render_alpha,
            self.photo_alpha
        )
    }
}
