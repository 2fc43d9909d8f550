//! PLY polyline strand files (in progress).
use std::path::Path;

use super::FormatError;
use crate::strands::Strands;

pub fn read_ply_strands(path: impl AsRef<Path>) -> Result<Strands, FormatError> {
    Err(FormatError::invalid(
        path.as_ref(),
        "PLY reading not implemented yet",
    ))
}

pub fn write_ply_strands(path: impl AsRef<Path>, _strands: &Strands) -> Result<(), FormatError> {
    Err(FormatError::invalid(
        path.as_ref(),
        "PLY writing not implemented yet",
    ))
}
