//! Bake techniques.

pub mod sdb;
