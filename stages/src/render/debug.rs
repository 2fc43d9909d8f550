//! (in progress) Writing renders to disk for inspection.
