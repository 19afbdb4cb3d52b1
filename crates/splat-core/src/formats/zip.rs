//! A small, strict ZIP reader and writer for `.sog` bundles (PKWARE APPNOTE 6.3: local file
//! headers, central directory, end-of-central-directory record).
//!
//! Reading trusts only the central directory (SOG writers put sizes in data descriptors after
//! each entry, so local headers hold zeros), checks every offset and size against the archive
//! before touching it, inflates `deflate` entries with a bound from the declared size, and
//! verifies each entry's CRC-32. Stored (method 0) and deflate (method 8) entries are supported;
//! encrypted entries and ZIP64 archives are refused with a clear error.
use std::path::Path;

use crate::error::{Error, Result};

const EOCD_SIG: u32 = 0x0605_4b50;
const CEN_SIG: u32 = 0x0201_4b50;
const LOC_SIG: u32 = 0x0403_4b50;
/// Magic of every ZIP archive that starts with a file entry.
pub const MAGIC: [u8; 4] = [0x50, 0x4b, 0x03, 0x04];
const DEFLATE_MAX_RATIO: u64 = 1032;

/// One file in the archive.
#[derive(Debug, Clone)]
pub struct Entry {
    pub name: String,
    method: u16,
    crc: u32,
    compressed: u64,
    size: u64,
    local_offset: u64,
}

/// An archive held in memory.
pub struct Zip<'a> {
    bytes: &'a [u8],
    path: &'a Path,
    pub entries: Vec<Entry>,
}

fn u16_at(b: &[u8], o: usize) -> u16 {
    u16::from_le_bytes([b[o], b[o + 1]])
}

fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}

impl<'a> Zip<'a> {
    /// Parse the central directory of `bytes` (`path` names the archive in errors).
    pub fn open(bytes: &'a [u8], path: &'a Path) -> Result<Self> {
        let err = |m: String| Error::format_at(path, "zip", None, m);
        // the end record is 22 bytes plus a comment of at most 65535
        let lo = bytes.len().saturating_sub(22 + 65_535);
        let eocd = (lo..=bytes.len().saturating_sub(22))
            .rev()
            .find(|&i| u32_at(bytes, i) == EOCD_SIG)
            .ok_or_else(|| {
                err(format!(
                    "no end-of-central-directory record in {} bytes (truncated or not a zip)",
                    bytes.len()
                ))
            })?;
        let count = u16_at(bytes, eocd + 10) as usize;
        let cd_size = u32_at(bytes, eocd + 12) as u64;
        let cd_off = u32_at(bytes, eocd + 16) as u64;
        if count == 0xffff || cd_size == 0xffff_ffff || cd_off == 0xffff_ffff {
            return Err(err("ZIP64 archives are not supported".into()));
        }
        if cd_off + cd_size > eocd as u64 {
            return Err(err(format!(
                "central directory at bytes {cd_off}..{} lies outside the archive (end record at \
                 {eocd}; truncated file?)",
                cd_off + cd_size
            )));
        }
        // every central entry is at least 46 bytes
        if count as u64 * 46 > cd_size {
            return Err(err(format!(
                "{count} entries cannot fit a {cd_size}-byte central directory"
            )));
        }
        let mut entries = Vec::with_capacity(count);
        let mut o = cd_off as usize;
        let end = (cd_off + cd_size) as usize;
        for i in 0..count {
            if o + 46 > end || u32_at(bytes, o) != CEN_SIG {
                return Err(err(format!("central directory entry {i} is corrupt")));
            }
            let flags = u16_at(bytes, o + 8);
            let method = u16_at(bytes, o + 10);
            let crc = u32_at(bytes, o + 16);
            let compressed = u32_at(bytes, o + 20) as u64;
            let size = u32_at(bytes, o + 24) as u64;
            let nlen = u16_at(bytes, o + 28) as usize;
            let xlen = u16_at(bytes, o + 30) as usize;
            let clen = u16_at(bytes, o + 32) as usize;
            let local_offset = u32_at(bytes, o + 42) as u64;
            if o + 46 + nlen > end {
                return Err(err(format!("central directory entry {i} is truncated")));
            }
            let name = String::from_utf8_lossy(&bytes[o + 46..o + 46 + nlen]).into_owned();
            if flags & 1 != 0 {
                return Err(err(format!("entry '{name}' is encrypted")));
            }
            entries.push(Entry {
                name,
                method,
                crc,
                compressed,
                size,
                local_offset,
            });
            o += 46 + nlen + xlen + clen;
        }
        Ok(Zip {
            bytes,
            path,
            entries,
        })
    }

    /// The entry called `name`, if any.
    pub fn entry(&self, name: &str) -> Option<&Entry> {
        self.entries.iter().find(|e| e.name == name)
    }

    /// The uncompressed bytes of entry `name`, checked against its size and CRC-32.
    pub fn read(&self, name: &str) -> Result<Vec<u8>> {
        let e = self.entry(name).ok_or_else(|| {
            Error::format_at(
                self.path,
                name,
                None,
                format!(
                    "not in the archive (it holds: {})",
                    self.entries
                        .iter()
                        .map(|e| e.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )
        })?;
        let err = |m: String| Error::format_at(self.path, name, None, m);
        let lo = e.local_offset as usize;
        if lo + 30 > self.bytes.len() || u32_at(self.bytes, lo) != LOC_SIG {
            return Err(err(format!(
                "local header at byte {lo} is missing or corrupt (truncated archive?)"
            )));
        }
        let start =
            lo + 30 + u16_at(self.bytes, lo + 26) as usize + u16_at(self.bytes, lo + 28) as usize;
        let stop = start as u64 + e.compressed;
        if stop > self.bytes.len() as u64 {
            return Err(err(format!(
                "data at bytes {start}..{stop} runs past the {}-byte archive (truncated?)",
                self.bytes.len()
            )));
        }
        let raw = &self.bytes[start..stop as usize];
        let data = match e.method {
            0 => {
                if e.size != e.compressed {
                    return Err(err(format!(
                        "stored entry declares {} bytes but holds {}",
                        e.size, e.compressed
                    )));
                }
                raw.to_vec()
            }
            8 => {
                if e.size > e.compressed.saturating_mul(DEFLATE_MAX_RATIO) + 1024 {
                    return Err(err(format!(
                        "{} deflated bytes cannot hold the {} bytes the directory declares",
                        e.compressed, e.size
                    )));
                }
                let (out, more) = super::read_bounded(
                    flate2::read::DeflateDecoder::new(raw),
                    e.size,
                    e.size,
                    self.path,
                    &format!("zip entry '{name}'"),
                )?;
                if more || out.len() as u64 != e.size {
                    return Err(err(format!(
                        "inflates to {}{} bytes, the directory says {}",
                        if more { "more than " } else { "" },
                        out.len(),
                        e.size
                    )));
                }
                out
            }
            m => {
                return Err(err(format!(
                    "compression method {m} is not supported (stored and deflate are)"
                )))
            }
        };
        let mut crc = flate2::Crc::new();
        crc.update(&data);
        if crc.sum() != e.crc {
            return Err(err(format!(
                "CRC-32 mismatch (0x{:08x} stored, 0x{:08x} computed): corrupt archive",
                e.crc,
                crc.sum()
            )));
        }
        Ok(data)
    }
}

/// Write `files` (name, bytes) as an uncompressed ZIP archive: WebP textures do not deflate.
pub fn write_stored(files: &[(&str, &[u8])], w: &mut dyn std::io::Write) -> std::io::Result<()> {
    let mut central = Vec::new();
    let mut offset: u64 = 0;
    let too_big = || std::io::Error::other("archive exceeds 4 GiB (ZIP64 is not written)");
    for (name, data) in files {
        let mut crc = flate2::Crc::new();
        crc.update(data);
        let size = u32::try_from(data.len()).map_err(|_| too_big())?;
        let off = u32::try_from(offset).map_err(|_| too_big())?;
        let nlen = name.len() as u16;
        let mut local = Vec::with_capacity(30 + name.len());
        local.extend_from_slice(&LOC_SIG.to_le_bytes());
        local.extend_from_slice(&20u16.to_le_bytes()); // version needed
        local.extend_from_slice(&0x0800u16.to_le_bytes()); // UTF-8 names
        local.extend_from_slice(&0u16.to_le_bytes()); // stored
        local.extend_from_slice(&0u16.to_le_bytes()); // time
        local.extend_from_slice(&0x21u16.to_le_bytes()); // date 1980-01-01
        local.extend_from_slice(&crc.sum().to_le_bytes());
        local.extend_from_slice(&size.to_le_bytes());
        local.extend_from_slice(&size.to_le_bytes());
        local.extend_from_slice(&nlen.to_le_bytes());
        local.extend_from_slice(&0u16.to_le_bytes());
        local.extend_from_slice(name.as_bytes());
        w.write_all(&local)?;
        w.write_all(data)?;
        central.extend_from_slice(&CEN_SIG.to_le_bytes());
        central.extend_from_slice(&20u16.to_le_bytes()); // made by
        central.extend_from_slice(&local[4..30]);
        central.extend_from_slice(&0u16.to_le_bytes()); // comment length
        central.extend_from_slice(&0u16.to_le_bytes()); // disk
        central.extend_from_slice(&0u16.to_le_bytes()); // internal attributes
        central.extend_from_slice(&0u32.to_le_bytes()); // external attributes
        central.extend_from_slice(&off.to_le_bytes());
        central.extend_from_slice(name.as_bytes());
        offset += local.len() as u64 + data.len() as u64;
    }
    let cd_off = u32::try_from(offset).map_err(|_| too_big())?;
    w.write_all(&central)?;
    let mut end = Vec::with_capacity(22);
    end.extend_from_slice(&EOCD_SIG.to_le_bytes());
    end.extend_from_slice(&[0, 0, 0, 0]); // disk numbers
    end.extend_from_slice(&(files.len() as u16).to_le_bytes());
    end.extend_from_slice(&(files.len() as u16).to_le_bytes());
    end.extend_from_slice(&(central.len() as u32).to_le_bytes());
    end.extend_from_slice(&cd_off.to_le_bytes());
    end.extend_from_slice(&0u16.to_le_bytes());
    w.write_all(&end)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_detects_corruption() {
        let files: [(&str, &[u8]); 2] = [("meta.json", b"{\"a\":1}"), ("x.webp", &[1, 2, 3, 4])];
        let mut buf = Vec::new();
        write_stored(&files, &mut buf).expect("write");
        let p = Path::new("t.sog");
        let z = Zip::open(&buf, p).expect("open");
        assert_eq!(z.read("meta.json").expect("read"), b"{\"a\":1}");
        assert_eq!(z.read("x.webp").expect("read"), vec![1, 2, 3, 4]);
        let mut bad = buf.clone();
        let at = bad
            .windows(4)
            .position(|w| w == [1, 2, 3, 4])
            .expect("data");
        bad[at] ^= 0xff;
        let e = Zip::open(&bad, p).expect("open").read("x.webp");
        assert!(e.expect_err("crc").to_string().contains("CRC-32"));
        let e = Zip::open(&buf[..buf.len() - 30], p)
            .err()
            .expect("truncated");
        assert!(e.to_string().contains("end-of-central-directory"), "{e}");
    }
}
