//! Import errors. Each names the place in the file that is wrong (mesh, primitive,
//! accessor, buffer, image) so a user can find it in their editor; none is a panic.

use thiserror::Error;

/// Where in the document a problem sits, e.g. `mesh 2 "Floor", primitive 0`.
#[derive(Clone, Debug, PartialEq)]
pub struct PrimitiveRef {
    pub mesh: usize,
    pub mesh_name: String,
    pub primitive: usize,
}

impl std::fmt::Display for PrimitiveRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.mesh_name.is_empty() {
            write!(f, "mesh {}, primitive {}", self.mesh, self.primitive)
        } else {
            write!(
                f,
                "mesh {} \"{}\", primitive {}",
                self.mesh, self.mesh_name, self.primitive
            )
        }
    }
}

#[derive(Debug, Error)]
pub enum ImportError {
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("not a glTF 2.0 file: {0}")]
    NotGltf(String),
    #[error("invalid glTF: {0}")]
    Invalid(String),
    #[error("buffer {buffer}: {problem}")]
    Buffer { buffer: usize, problem: String },
    #[error("image {image}: {problem}")]
    Image { image: usize, problem: String },
    #[error("{at}: accessor {accessor} ({attribute}): {problem}")]
    Accessor {
        at: PrimitiveRef,
        accessor: usize,
        attribute: String,
        problem: String,
    },
    #[error("{at}: {problem}")]
    Primitive { at: PrimitiveRef, problem: String },
    #[error("{0}")]
    Material(String),
    #[error("the scene has no triangles to bake{0}")]
    NoTriangles(String),
    /// Over a cap of [`super::import::ImportLimits`]; `what` names it (`triangles`,
    /// `texture size`).
    #[error("{detail}")]
    Limit { what: &'static str, detail: String },
}
