//! `.spz` extension records (nianticlabs/spz `extensions/README.md`, `splat-extensions.cc`).
//!
//! When header flag 0x2 is set, records `[u32 type][u32 byteLength][payload]` follow each other:
//! in v4 between the 32-byte header and the table of contents, in v1-v3 after the attribute
//! payload (inside the gzip stream). Known types:
//!
//! - `0xADBE0002` `SPZ_ADOBE_safe_orbit_camera`: three f32, elevation min/max (radians) and the
//!   minimum orbit radius; reported, not needed to decode.
//! - `0xADBE0003` `SPZ_ADOBE_coordinate_system`: one u32, the coordinate system the data is
//!   stored in (1-16, see [`CoordinateSystem`]); 0 means unspecified (RUB). Loading honours it.
//!
//! Unknown types are skipped by their length and reported, as the reference does. A record whose
//! length runs past the records' region is a malformed file.
use std::path::Path;

use super::{flip_axes, Scene};
use crate::error::{Error, Result};

pub const SAFE_ORBIT_CAMERA: u32 = 0xADBE_0002;
pub const COORDINATE_SYSTEM: u32 = 0xADBE_0003;

/// The 16 named axis conventions of nianticlabs/spz (`CoordinateSystem` in `splat-types.h`):
/// letters give the directions of +x, +y, +z. 1-8 are the standard family, 9-16 the rotated one
/// (y and z swapped by a 90-degree rotation about x).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[allow(clippy::upper_case_acronyms)]
pub enum CoordinateSystem {
    LDB = 1,
    RDB,
    LUB,
    RUB,
    LDF,
    RDF,
    LUF,
    RUF,
    LFD,
    RFD,
    LFU,
    RFU,
    LBD,
    RBD,
    LBU,
    RBU,
}

impl CoordinateSystem {
    fn from_u32(v: u32) -> Option<Self> {
        use CoordinateSystem::*;
        const ALL: [CoordinateSystem; 16] = [
            LDB, RDB, LUB, RUB, LDF, RDF, LUF, RUF, LFD, RFD, LFU, RFU, LBD, RBD, LBU, RBU,
        ];
        ALL.get((v as usize).checked_sub(1)?).copied()
    }
}

/// One parsed record.
#[derive(Debug, Clone, PartialEq)]
pub enum Record {
    SafeOrbitCamera {
        elevation_min: f32,
        elevation_max: f32,
        radius_min: f32,
    },
    CoordinateSystem(u32),
    Unknown {
        kind: u32,
        len: usize,
    },
}

fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}

/// Parse the extension region. Every record must fit in it.
pub fn parse(bytes: Vec<u8>, path: &Path) -> Result<Vec<Record>> {
    let mut out = Vec::new();
    let mut o = 0;
    while o < bytes.len() {
        if o + 8 > bytes.len() {
            return Err(Error::format_at(
                path,
                "spz extensions",
                None,
                format!(
                    "{} stray bytes where an extension record header (8 bytes) should be",
                    bytes.len() - o
                ),
            ));
        }
        let kind = u32_at(&bytes, o);
        let len = u32_at(&bytes, o + 4) as usize;
        let body = o + 8;
        if len > bytes.len() - body {
            return Err(Error::format_at(
                path,
                "spz extensions",
                None,
                format!(
                    "record 0x{kind:08x} declares {len} payload bytes but only {} remain",
                    bytes.len() - body
                ),
            ));
        }
        let p = &bytes[body..body + len];
        let f = |i: usize| f32::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]);
        let rec = match (kind, len) {
            (SAFE_ORBIT_CAMERA, 12) => Record::SafeOrbitCamera {
                elevation_min: f(0),
                elevation_max: f(4),
                radius_min: f(8),
            },
            (COORDINATE_SYSTEM, 4) => Record::CoordinateSystem(u32_at(p, 0)),
            (SAFE_ORBIT_CAMERA | COORDINATE_SYSTEM, _) => {
                return Err(Error::format_at(
                    path,
                    "spz extensions",
                    None,
                    format!("record 0x{kind:08x} has a {len}-byte payload (wrong size)"),
                ))
            }
            _ => Record::Unknown { kind, len },
        };
        out.push(rec);
        o = body + len;
    }
    Ok(out)
}

/// The axes the data is stored in: RUB unless a coordinate-system record says otherwise.
pub fn stored_axes(records: &[Record], path: &Path) -> Result<CoordinateSystem> {
    for r in records {
        if let Record::CoordinateSystem(v) = *r {
            if v == 0 {
                return Ok(CoordinateSystem::RUB);
            }
            return CoordinateSystem::from_u32(v).ok_or_else(|| {
                Error::format_at(
                    path,
                    "spz extensions",
                    Some("SPZ_ADOBE_coordinate_system"),
                    format!("coordinate system {v} is not one of 1-16"),
                )
            });
        }
    }
    Ok(CoordinateSystem::RUB)
}

/// Human-readable notes about the records (the binding turns them into warnings).
pub fn notes(records: &[Record], path: &Path) -> Vec<String> {
    records
        .iter()
        .filter_map(|r| match *r {
            Record::SafeOrbitCamera {
                elevation_min,
                elevation_max,
                radius_min,
            } => Some(format!(
                "{}: .spz SPZ_ADOBE_safe_orbit_camera: elevation {elevation_min}..{elevation_max} \
                 rad, minimum radius {radius_min} (informational; not applied)",
                path.display()
            )),
            Record::Unknown { kind, len } => Some(format!(
                "{}: skipped unknown .spz extension record 0x{kind:08x} ({len} bytes)",
                path.display()
            )),
            Record::CoordinateSystem(_) => None,
        })
        .collect()
}

/// Convert a scene stored in `from` to RDF. Standard-family systems differ from RDF by axis
/// mirrors only; the rotated family (LFD..RBU) also needs a 90-degree rotation of positions,
/// rotations and every SH band, which is not implemented and is refused.
pub fn to_rdf(scene: &mut Scene, from: CoordinateSystem, path: &Path) -> Result<()> {
    let code = from as u32 - 1;
    if code >= 8 {
        return Err(Error::format_at(
            path,
            "spz extensions",
            Some("SPZ_ADOBE_coordinate_system"),
            format!(
                "data stored in {from:?}, a rotated coordinate system: converting it is not \
                 supported; load with spz_axes=\"stored\" to get the stored axes"
            ),
        ));
    }
    flip_axes(scene, mirrors(code, CoordinateSystem::RDF as u32 - 1));
    Ok(())
}

/// Mirrors taking standard system `a` to standard system `b` (bit 0: x right, bit 1: y up,
/// bit 2: z front).
fn mirrors(a: u32, b: u32) -> [f32; 3] {
    [0, 1, 2].map(|bit| {
        if (a >> bit) & 1 == (b >> bit) & 1 {
            1.0
        } else {
            -1.0
        }
    })
}

/// The bytes of a coordinate-system record (for tests and writers).
pub fn coordinate_system_record(cs: u32) -> Vec<u8> {
    let mut v = COORDINATE_SYSTEM.to_le_bytes().to_vec();
    v.extend_from_slice(&4u32.to_le_bytes());
    v.extend_from_slice(&cs.to_le_bytes());
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rub_to_rdf_is_the_y_z_flip() {
        assert_eq!(
            mirrors(CoordinateSystem::RUB as u32 - 1, 5),
            [1.0, -1.0, -1.0]
        );
        assert_eq!(
            mirrors(CoordinateSystem::LUF as u32 - 1, 5),
            [-1.0, -1.0, 1.0]
        );
    }

    #[test]
    fn records_parse_and_lying_lengths_fail() {
        let p = Path::new("x.spz");
        let mut b = coordinate_system_record(6);
        b.extend_from_slice(&0x1234_0001u32.to_le_bytes());
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(&[7, 7]);
        let r = parse(b.clone(), p).expect("parse");
        assert_eq!(
            r,
            vec![
                Record::CoordinateSystem(6),
                Record::Unknown {
                    kind: 0x1234_0001,
                    len: 2
                }
            ]
        );
        assert_eq!(stored_axes(&r, p).expect("axes"), CoordinateSystem::RDF);
        b.truncate(b.len() - 1);
        assert!(parse(b, p).is_err());
    }
}
