//! Format detection: `load` looks at the content (magic bytes and header), not the extension.
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use crate::error::{Error, Result};
use crate::ply::{self, OnInvalid};
use crate::scene::Scene;

pub use crate::ply::LoadReport;

/// Options shared by every reader.
#[derive(Debug, Clone, Copy, Default)]
pub struct LoadOptions {
    pub on_invalid: OnInvalid,
}

/// Load a scene from any supported format, detected from the file's content.
pub fn load(path: &Path, opts: LoadOptions) -> Result<(Scene, LoadReport)> {
    let mut magic = [0u8; 16];
    let n = {
        let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
        if f.metadata().map_err(|e| Error::io(path, e))?.is_dir() {
            return Err(Error::io(
                path,
                std::io::Error::new(std::io::ErrorKind::IsADirectory, "is a directory"),
            ));
        }
        read_up_to(&mut f, &mut magic).map_err(|e| Error::io(path, e))?
    };
    let magic = &magic[..n];
    if ply::is_ply(magic) {
        return ply::read_ply(path, opts.on_invalid);
    }
    if n == 0 {
        return Err(Error::format(path, "the file is empty"));
    }
    Err(Error::format(
        path,
        format!(
            "unrecognised scene format (first bytes {}); supported: INRIA 3DGS PLY",
            hex(magic)
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
