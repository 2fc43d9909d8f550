//! (in progress) The `synthetic_scene` stage.
pub mod body;
pub mod fur;
pub mod presets;
