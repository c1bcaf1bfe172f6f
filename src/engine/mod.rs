pub mod gpu;
pub mod scene;
pub mod technique;
