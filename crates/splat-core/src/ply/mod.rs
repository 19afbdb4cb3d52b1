//! INRIA-layout PLY: a header parser shared with the other PLY dialects, a parallel reader that
//! finds properties by name (binary little/big-endian and ASCII, any numeric type) and an atomic
//! writer.
//!
//! The reader never trusts the header: the vertex count is checked against the bytes the file can
//! hold before anything is allocated, and the body is decoded in fixed-size tasks, so peak memory
//! is the output arrays plus one scratch buffer per thread.
mod header;
mod pio;
mod plan;
mod read;
mod write;

pub use header::{
    is_ply, read_header, Element, Encoding, Header, Property, PropertyKind, ScalarType,
};
pub use plan::is_standard_name;
pub use read::{read_ply, LoadReport, OnInvalid};
pub use write::{atomic_write, atomic_write_file, check_extra_names, write_ply};

#[cfg(test)]
mod tests;
