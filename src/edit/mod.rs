pub mod crop;
pub mod mesh;
