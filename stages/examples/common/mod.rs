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
