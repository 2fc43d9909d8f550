//! Cem Yuksel `.hair` strand files (in progress).
use std::path::Path;

use super::FormatError;
use crate::strands::Strands;

pub fn read_hair(path: impl AsRef<Path>) -> Result<Strands, FormatError> {
    Err(FormatError::invalid(
        path.as_ref(),
        ".hair reading not implemented yet",
    ))
}

pub fn write_hair(path: impl AsRef<Path>, _strands: &Strands) -> Result<(), FormatError> {
    Err(FormatError::invalid(
        path.as_ref(),
        ".hair writing not implemented yet",
    ))
}
