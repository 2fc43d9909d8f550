//! Wavefront OBJ meshes (in progress).
use std::path::Path;

use super::FormatError;
use crate::mesh::Mesh;

pub fn read_obj(path: impl AsRef<Path>) -> Result<Mesh, FormatError> {
    Err(FormatError::invalid(
        path.as_ref(),
        "OBJ reading not implemented yet",
    ))
}

pub fn write_obj(path: impl AsRef<Path>, _mesh: &Mesh) -> Result<(), FormatError> {
    Err(FormatError::invalid(
        path.as_ref(),
        "OBJ writing not implemented yet",
    ))
}
