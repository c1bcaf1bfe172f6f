//! lightmapd: a lightmap baker. The engine (`engine`) turns a glTF scene into lightmaps
//! and knows nothing of HTTP, SQL or storage; `bench` measures the engine's techniques;
//! `service` will serve bake jobs over HTTP.

pub mod bench;
pub mod engine;
pub mod service;
