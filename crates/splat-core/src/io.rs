//! Format detection: `load` looks at the content (magic bytes and header), not the extension.
//!
//! - `ply\n`: a PLY; a `chunk` element plus packed `vertex` properties make it a SuperSplat
//!   compressed PLY, anything else is read as an INRIA 3DGS PLY.
//! - `NGSP` (plain) or a gzip stream (`1f 8b`): Niantic `.spz`.
//! - `glTF`: a GLB; `{`: JSON, either a glTF document (`asset` and `meshes`) or a SOG
//!   `meta.json` (`means` and `quats`, textures beside it);
//! - `PK\x03\x04`: a ZIP holding a `meta.json`: a bundled PlayCanvas `.sog`;
//! - a directory: a SceneSplat `.npy` folder (`coord.npy` ...) or an unbundled SOG (`meta.json`);
//! - otherwise a non-empty file whose size is a multiple of 32 and whose first records hold
//!   plausible positions and scales: antimatter15 `.splat` (a format without magic).
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use crate::error::{Error, Result};
use crate::formats::{compressed_ply, gltf, scenesplat, sog, splat, spz, zip, SpzAxes};
use crate::ply::{self, OnInvalid};
use crate::scene::Scene;

pub use crate::ply::LoadReport;

/// Options shared by every reader.
#[derive(Debug, Clone, Copy, Default)]
pub struct LoadOptions {
    pub on_invalid: OnInvalid,
    /// Axes of `.spz` scenes: converted to RDF (default) or kept as stored (RUB).
    pub spz_axes: SpzAxes,
}

/// Load a scene from any supported format, detected from the file's content.
pub fn load(path: &Path, opts: LoadOptions) -> Result<(Scene, LoadReport)> {
    let mut magic = [0u8; 16];
    let (n, len) = {
        let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
        let meta = f.metadata().map_err(|e| Error::io(path, e))?;
        if meta.is_dir() {
            return load_dir(path, opts);
        }
        (
            read_up_to(&mut f, &mut magic).map_err(|e| Error::io(path, e))?,
            meta.len(),
        )
    };
    let magic = &magic[..n];
    if ply::is_ply(magic) {
        let header = {
            let mut r = open(path)?;
            ply::read_header(&mut r, path)?
        };
        if compressed_ply::is_compressed(&header) {
            let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
            return compressed_ply::read(path, &header, &bytes, opts.on_invalid);
        }
        return ply::read_ply(path, opts.on_invalid);
    }
    if n == 0 {
        return Err(Error::format(path, "the file is empty"));
    }
    if magic.starts_with(&spz::MAGIC.to_le_bytes()) || magic.starts_with(&spz::GZIP_MAGIC) {
        return spz::read(path, opts.spz_axes);
    }
    if magic.starts_with(&gltf::GLB_MAGIC.to_le_bytes()) {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        return gltf::read(&bytes, path, opts.on_invalid);
    }
    if magic.starts_with(&zip::MAGIC) {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        if sog::zip_has_meta(&bytes, path) {
            return sog::read_zip(&bytes, path, opts.on_invalid);
        }
        // a damaged archive: say what is wrong with it
        zip::Zip::open(&bytes, path)?;
        return Err(unrecognised(
            path,
            magic,
            len,
            "a ZIP archive without a SOG meta.json; ",
        ));
    }
    if magic.trim_ascii_start().starts_with(b"{") && len < MAX_JSON {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        if gltf::looks_like_gltf_json(&bytes) {
            return gltf::read(&bytes, path, opts.on_invalid);
        }
        if sog::looks_like_meta(&bytes) {
            return sog::read_dir(path, opts.on_invalid);
        }
        if serde_json::from_slice::<serde_json::Value>(&bytes).is_ok() {
            return Err(Error::format(
                path,
                "a JSON file that is neither a glTF document (asset, meshes) nor a SOG \
                 meta.json (means, quats)",
            ));
        }
    }
    if len % splat::RECORD_BYTES as u64 == 0 {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        match splat::looks_like_splat(&bytes) {
            None => {
                let scene = splat::decode(&bytes);
                drop(bytes);
                return crate::formats::finish(scene, "splat", "splat", path, opts.on_invalid);
            }
            Some(why) => {
                return Err(Error::format(
                    path,
                    format!(
                        "unrecognised scene format: no known magic (first bytes {}), and as an \
                         antimatter15 .splat {why}",
                        hex(magic)
                    ),
                ))
            }
        }
    }
    Err(unrecognised(path, magic, len, ""))
}

fn unrecognised(path: &Path, magic: &[u8], len: u64, what: &str) -> Error {
    Error::format(
        path,
        format!(
            "unrecognised scene format ({what}first bytes {}); supported: INRIA 3DGS PLY, SuperSplat \
             compressed PLY, Niantic .spz (v1-v4), PlayCanvas SOG (.sog or meta.json), glTF/GLB \
             with KHR_gaussian_splatting, SceneSplat .npy folders, antimatter15 .splat (size a \
             multiple of 32, this file has {len} bytes)",
            hex(magic)
        ),
    )
}

/// JSON documents (glTF, SOG meta.json) larger than this are not sniffed.
const MAX_JSON: u64 = 256 << 20;

/// A directory: a SceneSplat `.npy` folder or an unbundled SOG.
fn load_dir(path: &Path, opts: LoadOptions) -> Result<(Scene, LoadReport)> {
    if scenesplat::is_scenesplat_dir(path) {
        return scenesplat::read(path, opts.on_invalid);
    }
    if path.join("meta.json").is_file() {
        return sog::read_dir(path, opts.on_invalid);
    }
    Err(Error::io(
        path,
        std::io::Error::new(
            std::io::ErrorKind::IsADirectory,
            "is a directory, but neither a SceneSplat .npy folder (coord.npy, color.npy, \
             opacity.npy, scale.npy, quat.npy) nor an unbundled SOG (meta.json and its textures)",
        ),
    ))
}

fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..])? {
            0 => break,
            k => got += k,
        }
    }
    Ok(got)
}

fn hex(b: &[u8]) -> String {
    b.iter()
        .take(8)
        .map(|x| format!("{x:02x}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// A buffered reader for a path, mapping errors to [`Error::Io`].
pub fn open(path: &Path) -> Result<BufReader<File>> {
    let f = File::open(path).map_err(|e| Error::io(path, e))?;
    Ok(BufReader::with_capacity(1 << 20, f))
}
