//! The techniques, behind one trait, registered in one table.
//!
//! Layout (docs/architecture.md): each technique is whole in its own folder,
//! `technique/<id>/` (its module doc in `mod.rs`, further files only along real concepts)
//! with its WGSL in `shaders/<id>/`. The contract every technique implements is in
//! [`api`]; the table that registers them is [`table`]. A technique imports [`api`] and the
//! shared layers below it (`gpu`, `atlas`, `scene`, `accumulate`, …), never another
//! technique and never this module's root: `tests/architecture.rs` checks it.
//!
//! Every layer holds irradiance / π at the texel's sample point (the outgoing radiance of
//! a white Lambertian surface), not including the surface's own emission.

pub mod api;
pub mod table;

pub mod hemicube;
pub mod obscurance;
pub mod path;
pub mod sdb;
pub mod sdf;
pub mod vpl;

pub use api::{AlphaSupport, BakeInputs, Boundary, EngineError, Technique, gpu_error, parse_params};
pub use table::{LightSource, TABLE, TECHNIQUES, TechniqueEntry, check_lights, check_request, create, entry, plan};
