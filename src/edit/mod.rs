pub mod compose;
pub mod crop;
pub mod mesh;
