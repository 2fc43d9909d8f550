//! (in progress) Losses with gradients.
