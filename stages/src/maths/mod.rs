//! Mathematics several stages share: spatial queries and statistics. (The differentiable
//! renderer, the largest shared piece, is [`crate::render`].)

pub mod geom;
pub mod stats;
