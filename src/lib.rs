//! The fure engine.
