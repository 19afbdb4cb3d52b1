//! Checkpoints: everything the loop needs to continue exactly where it stopped (step count,
//! parameters, Adam moments, densification statistics), written atomically (a temporary file,
//! fsync, rename), so a kill at any moment leaves the previous checkpoint or the new one.
//!
//! Layout (little-endian): magic `MGSFITCK`, u32 version (1), u64 fingerprint length and bytes
//! (the caller's identity of the run: config and data; a mismatch is refused on load), u32
//! completed steps, u64 N, u8 SH degree, then per parameter array u32 width and values, first
//! moments, second moments (N * width f32 each), then u32 statistics length S (0 or N) and four
//! arrays of S f32 (grad2d, grad2d_abs, count, max_radius), then a u64 FNV-1a hash of every byte
//! before it. Sizes are checked against the file length before anything is allocated.
use std::io::Write;
use std::path::Path;

use crate::error::{Error, Result};
use crate::ply::atomic_write;
use crate::raster::diff::DensifyStats;
use crate::scene::sh_rest_count;

use super::params::{Group, Params, GROUPS, NAMES};

const MAGIC: &[u8; 8] = b"MGSFITCK";
const VERSION: u32 = 1;

/// The restorable state of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct Checkpoint {
    pub fingerprint: Vec<u8>,
    pub step: u32,
    pub params: Params,
    pub stats: DensifyStats,
}

fn fnv1a(h: u64, bytes: &[u8]) -> u64 {
    let mut h = h;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

const FNV_START: u64 = 0xcbf2_9ce4_8422_2325;

/// A writer that hashes what passes through it.
struct Hashing<'a> {
    w: &'a mut dyn Write,
    h: u64,
}

impl Write for Hashing<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.w.write(buf)?;
        self.h = fnv1a(self.h, &buf[..n]);
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.w.flush()
    }
}

fn put_f32s(w: &mut dyn Write, v: &[f32]) -> std::io::Result<()> {
    for chunk in v.chunks(1 << 14) {
        let mut buf = Vec::with_capacity(chunk.len() * 4);
        for x in chunk {
            buf.extend_from_slice(&x.to_le_bytes());
        }
        w.write_all(&buf)?;
    }
    Ok(())
}

/// Write `ck` to `path` atomically.
pub fn save(path: &Path, ck: &Checkpoint) -> Result<()> {
    let p = &ck.params;
    let n = p.len();
    atomic_write(path, |out| {
        let mut w = Hashing {
            w: out,
            h: FNV_START,
        };
        w.write_all(MAGIC)?;
        w.write_all(&VERSION.to_le_bytes())?;
        w.write_all(&(ck.fingerprint.len() as u64).to_le_bytes())?;
        w.write_all(&ck.fingerprint)?;
        w.write_all(&ck.step.to_le_bytes())?;
        w.write_all(&(n as u64).to_le_bytes())?;
        w.write_all(&[p.sh_degree])?;
        for g in &p.groups {
            w.write_all(&(g.width as u32).to_le_bytes())?;
            put_f32s(&mut w, &g.value)?;
            put_f32s(&mut w, &g.m)?;
            put_f32s(&mut w, &g.v)?;
        }
        let s = &ck.stats;
        let slen = if s.count.len() == n { n } else { 0 };
        w.write_all(&(slen as u32).to_le_bytes())?;
        if slen > 0 {
            for v in [&s.grad2d, &s.grad2d_abs, &s.count, &s.max_radius] {
                put_f32s(&mut w, v)?;
            }
        }
        let h = w.h;
        out_hash(w.w, h)
    })
}

fn out_hash(w: &mut dyn Write, h: u64) -> std::io::Result<()> {
    w.write_all(&h.to_le_bytes())
}

/// A cursor over the file's bytes that reports truncation as a format error.
struct Reader<'a> {
    b: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        if self.b.len() - self.at < n {
            return Err(Error::format(
                self.path,
                format!("checkpoint truncated while reading {what}"),
            ));
        }
        let s = &self.b[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        let b = self.take(8, what)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(u64::from_le_bytes(a))
    }
    fn f32s(&mut self, count: usize, what: &str) -> Result<Vec<f32>> {
        let bytes = count
            .checked_mul(4)
            .ok_or_else(|| Error::format(self.path, format!("{what}: size overflows")))?;
        let b = self.take(bytes, what)?;
        Ok(b.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }
}

/// Read a checkpoint; `fingerprint` must equal the one it was saved with.
pub fn load(path: &Path, fingerprint: &[u8]) -> Result<Checkpoint> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    if bytes.len() < MAGIC.len() + 12 || &bytes[..8] != MAGIC {
        return Err(Error::format(path, "not a morphgs fit checkpoint"));
    }
    let body = &bytes[..bytes.len() - 8];
    let mut hb = [0u8; 8];
    hb.copy_from_slice(&bytes[bytes.len() - 8..]);
    if fnv1a(FNV_START, body) != u64::from_le_bytes(hb) {
        return Err(Error::format(path, "checkpoint is corrupt (hash mismatch)"));
    }
    let mut r = Reader {
        b: body,
        at: 8,
        path,
    };
    let version = r.u32("the version")?;
    if version != VERSION {
        return Err(Error::format(
            path,
            format!("checkpoint version {version} is not supported (expected {VERSION})"),
        ));
    }
    let flen = r.u64("the fingerprint length")? as usize;
    let fp = r.take(flen, "the fingerprint")?.to_vec();
    if fp != fingerprint {
        return Err(Error::format(
            path,
            "checkpoint belongs to a run with another config or other data",
        ));
    }
    let step = r.u32("the step")?;
    let n = r.u64("the Gaussian count")? as usize;
    let sh_degree = r.take(1, "the SH degree")?[0];
    if sh_degree > 3 {
        return Err(Error::format(
            path,
            format!("SH degree {sh_degree} out of range"),
        ));
    }
    let k = sh_rest_count(sh_degree) * 3;
    let widths = [3usize, 4, 3, 1, 3, k];
    // the parameter block alone needs 12 bytes per value: refuse a lying count before allocating
    let per = widths.iter().sum::<usize>() * 12;
    if n.checked_mul(per).is_none_or(|b| b > body.len()) {
        return Err(Error::format(
            path,
            format!("checkpoint claims {n} Gaussians, more than the file holds"),
        ));
    }
    let mut groups: Vec<Group> = Vec::with_capacity(GROUPS);
    for (g, &want) in widths.iter().enumerate() {
        let w = r.u32(NAMES[g])? as usize;
        if w != want {
            return Err(Error::format(
                path,
                format!("array {} has width {w}, expected {want}", NAMES[g]),
            ));
        }
        let value = r.f32s(n * w, NAMES[g])?;
        let m = r.f32s(n * w, NAMES[g])?;
        let v = r.f32s(n * w, NAMES[g])?;
        groups.push(Group {
            width: w,
            value,
            m,
            v,
        });
    }
    let slen = r.u32("the statistics length")? as usize;
    if slen != 0 && slen != n {
        return Err(Error::format(
            path,
            "statistics length does not match the Gaussians",
        ));
    }
    let mut stats = DensifyStats::default();
    stats.reset(n);
    if slen > 0 {
        stats.grad2d = r.f32s(n, "grad2d")?;
        stats.grad2d_abs = r.f32s(n, "grad2d_abs")?;
        stats.count = r.f32s(n, "count")?;
        stats.max_radius = r.f32s(n, "max_radius")?;
    }
    if r.at != body.len() {
        return Err(Error::format(path, "trailing bytes after the checkpoint"));
    }
    let groups: [Group; GROUPS] = groups
        .try_into()
        .map_err(|_| Error::format(path, "wrong number of arrays"))?;
    Ok(Checkpoint {
        fingerprint: fp,
        step,
        params: Params { groups, sh_degree },
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Scene;

    #[test]
    fn round_trip_and_refusals() {
        let mut s = Scene::zeroed(5, 2);
        s.means[4] = 3.5;
        let mut params = Params::from_view(&s.view());
        params.groups[5].m[7] = -1.25;
        let mut stats = DensifyStats::default();
        stats.reset(5);
        stats.count[2] = 4.0;
        let ck = Checkpoint {
            fingerprint: b"cfg".to_vec(),
            step: 42,
            params,
            stats,
        };
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("ck.bin");
        save(&path, &ck).expect("save");
        assert_eq!(load(&path, b"cfg").expect("load"), ck);
        assert!(load(&path, b"other").is_err());
        let mut bytes = std::fs::read(&path).expect("read");
        let last = bytes.len() - 20;
        bytes[last] ^= 1;
        std::fs::write(&path, &bytes).expect("write");
        assert!(matches!(load(&path, b"cfg"), Err(Error::Format { .. })));
        std::fs::write(&path, &bytes[..100]).expect("write");
        assert!(load(&path, b"cfg").is_err());
    }
}
