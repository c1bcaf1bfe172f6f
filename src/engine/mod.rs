//! The bake engine: everything between a glTF scene and a lightmap, with no knowledge of
//! HTTP, SQL or storage (DESIGN §1). A bake is: [`scene`] import → [`atlas`] texel set →
//! a [`technique`] stepped by [`bake`] into the half-accumulators of [`accumulate`] →
//! [`post`] dilation → [`output`] EXR; [`tasks`] splits one bake over several workers.

pub mod accumulate;
pub mod ambient;
pub mod atlas;
pub mod bake;
pub mod control;
pub mod error;
pub mod footprint;
pub mod gpu;
pub mod job;
pub mod output;
pub mod plan;
pub mod post;
pub mod raytrace;
pub mod reference;
pub mod rng;
pub mod rounds;
pub mod scene;
pub mod shadowmask;
pub mod tasks;
pub mod technique;
