//! Which PLY property feeds which scene array, and the decode kernels that move a tile of rows
//! (every property already cast to float32, one row after another) into the scene arrays.
use std::path::Path;

use crate::error::{Error, Result};
use crate::scene::{normalize_quats, sh_degree_for_rest, sh_rest_count, Scene};

use super::header::{Element, PropertyKind};

/// The destination array of a field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dest {
    Means,
    Sh0,
    Opacity,
    LogScales,
    Quats,
    ShRest,
    Extra(usize),
}

/// How a field's columns are laid out in the source row.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Gather {
    /// `width` consecutive properties starting at `base`.
    Contiguous(usize),
    /// f_rest: the file is channel-major (all R, then G, then B, `k` each, from `base`); the scene
    /// is basis-major, channel-last.
    RestTransposed { base: usize, k: usize },
    /// Any other arrangement: the source column of each destination column.
    Columns(Vec<usize>),
}

/// One destination array and where its values come from.
#[derive(Debug, Clone)]
pub struct Field {
    pub dest: Dest,
    /// Values per Gaussian.
    pub width: usize,
    /// Source property index of each destination column.
    pub cols: Vec<usize>,
    pub gather: Gather,
}

/// The decode plan of a vertex element.
#[derive(Debug, Clone)]
pub struct Plan {
    /// Means, Sh0, Opacity, LogScales, Quats, ShRest, then one field per extra property.
    pub fields: Vec<Field>,
    pub sh_degree: u8,
    pub extra_names: Vec<String>,
    /// Property names of the element, by index (for error messages).
    pub names: Vec<String>,
}

/// Index of the quaternion field, and of the first extra field, in `Plan::fields`.
pub const QUATS_FIELD: usize = 4;
pub const STANDARD_FIELDS: usize = 6;

const NORMALS: [&str; 3] = ["nx", "ny", "nz"];
const GROUPS: [(Dest, &[&str]); 5] = [
    (Dest::Means, &["x", "y", "z"]),
    (Dest::Sh0, &["f_dc_0", "f_dc_1", "f_dc_2"]),
    (Dest::Opacity, &["opacity"]),
    (Dest::LogScales, &["scale_0", "scale_1", "scale_2"]),
    (Dest::Quats, &["rot_0", "rot_1", "rot_2", "rot_3"]),
];

/// `f_rest_<digits>`: a higher-band SH coefficient (anything else starting `f_rest_` is an extra).
fn is_rest_name(name: &str) -> bool {
    name.strip_prefix("f_rest_")
        .is_some_and(|d| !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()))
}

/// Every standard property name the INRIA layout uses (extras may not take these names).
pub fn is_standard_name(name: &str) -> bool {
    NORMALS.contains(&name)
        || GROUPS.iter().any(|(_, names)| names.contains(&name))
        || is_rest_name(name)
}

fn gather_of(cols: &[usize]) -> Gather {
    match cols.first() {
        Some(&b) if cols.iter().enumerate().all(|(i, &c)| c == b + i) => Gather::Contiguous(b),
        None => Gather::Contiguous(0),
        _ => Gather::Columns(cols.to_vec()),
    }
}

/// Map the vertex element's properties (found by name) to the scene arrays.
pub fn plan_vertex(element: &Element, path: &Path) -> Result<Plan> {
    let vname = element.name.as_str();
    let at = |prop: Option<&str>, msg: String| Error::format_at(path, vname, prop, msg);
    if let Some(p) = element
        .properties
        .iter()
        .find(|p| matches!(p.kind, PropertyKind::List(..)))
    {
        return Err(at(
            Some(&p.name),
            "is a list property; list properties are not supported in the vertex element".into(),
        ));
    }
    for (i, p) in element.properties.iter().enumerate() {
        if element.properties[..i].iter().any(|q| q.name == p.name) {
            return Err(at(Some(&p.name), "the property is declared twice".into()));
        }
    }
    let idx = |name: &str| element.property(name).map(|(i, _)| i);
    let missing: Vec<&str> = GROUPS
        .iter()
        .flat_map(|(_, names)| names.iter().copied())
        .filter(|n| idx(n).is_none())
        .collect();
    if !missing.is_empty() {
        return Err(at(
            None,
            format!(
                "missing required properties: {} (an INRIA 3DGS PLY has x y z, f_dc_0..2, \
                 opacity, scale_0..2, rot_0..3)",
                missing.join(", ")
            ),
        ));
    }
    let mut fields: Vec<Field> = GROUPS
        .iter()
        .map(|(d, names)| {
            let cols: Vec<usize> = names.iter().filter_map(|n| idx(n)).collect();
            Field {
                dest: *d,
                width: names.len(),
                gather: gather_of(&cols),
                cols,
            }
        })
        .collect();

    let n_rest = element
        .properties
        .iter()
        .filter(|p| is_rest_name(&p.name))
        .count();
    let Some(sh_degree) = (n_rest % 3 == 0)
        .then(|| sh_degree_for_rest(n_rest / 3))
        .flatten()
    else {
        return Err(at(
            Some("f_rest_*"),
            format!(
                "{n_rest} f_rest properties is no SH degree (expected 0, 9, 24, 45 or 72 for \
                 degree 0 to 4)"
            ),
        ));
    };
    let k = sh_rest_count(sh_degree);
    let mut rest_cols = vec![0usize; 3 * k];
    for c in 0..3 {
        for j in 0..k {
            let name = format!("f_rest_{}", c * k + j);
            let Some(i) = idx(&name) else {
                return Err(at(
                    Some(&name),
                    format!("missing (the file has {n_rest} f_rest properties but not this one)"),
                ));
            };
            rest_cols[j * 3 + c] = i;
        }
    }
    let gather = match rest_cols.first() {
        Some(&base) if (0..3).all(|c| (0..k).all(|j| rest_cols[j * 3 + c] == base + c * k + j)) => {
            Gather::RestTransposed { base, k }
        }
        None => Gather::Contiguous(0),
        _ => Gather::Columns(rest_cols.clone()),
    };
    fields.push(Field {
        dest: Dest::ShRest,
        width: 3 * k,
        cols: rest_cols,
        gather,
    });

    let mut extra_names = Vec::new();
    for (i, p) in element.properties.iter().enumerate() {
        if !is_standard_name(&p.name) {
            fields.push(Field {
                dest: Dest::Extra(extra_names.len()),
                width: 1,
                cols: vec![i],
                gather: Gather::Contiguous(i),
            });
            extra_names.push(p.name.clone());
        }
    }
    Ok(Plan {
        fields,
        sh_degree,
        extra_names,
        names: element.properties.iter().map(|p| p.name.clone()).collect(),
    })
}

impl Plan {
    /// Zeroed output arrays for `n` Gaussians, one per field.
    pub fn alloc(&self, n: usize) -> Vec<Vec<f32>> {
        self.fields
            .iter()
            .map(|f| crate::mem::zeroed_f32(n * f.width))
            .collect()
    }

    /// Assemble the scene from the arrays `alloc` made.
    pub fn assemble(&self, outs: Vec<Vec<f32>>) -> Scene {
        let mut scene = Scene::empty(self.sh_degree);
        let mut extras: Vec<(String, Vec<f32>)> = Vec::with_capacity(self.extra_names.len());
        for (f, v) in self.fields.iter().zip(outs) {
            match f.dest {
                Dest::Means => scene.means = v,
                Dest::Sh0 => scene.sh0 = v,
                Dest::Opacity => scene.opacity_logits = v,
                Dest::LogScales => scene.log_scales = v,
                Dest::Quats => scene.quats = v,
                Dest::ShRest => scene.sh_rest = v,
                Dest::Extra(i) => extras.push((self.extra_names[i].clone(), v)),
            }
        }
        scene.extras = extras;
        scene
    }

    /// The file property holding column `col` of field `field`.
    pub fn property_name(&self, field: usize, col: usize) -> &str {
        self.fields
            .get(field)
            .and_then(|f| f.cols.get(col))
            .and_then(|&i| self.names.get(i))
            .map_or("?", String::as_str)
    }

    /// Decode `rows` (row-major, `stride` float32 values per row) into Gaussians `first..` of
    /// `outs` (one slice per field), normalise the quaternions, and return whether every standard
    /// value is finite.
    pub fn decode(
        &self,
        rows: &[f32],
        stride: usize,
        outs: &mut [&mut [f32]],
        first: usize,
    ) -> bool {
        let n = rows.len() / stride.max(1);
        let mut finite = true;
        for (fi, (f, out)) in self.fields.iter().zip(outs.iter_mut()).enumerate() {
            if f.width == 0 {
                continue;
            }
            let out = &mut out[first * f.width..(first + n) * f.width];
            match (&f.gather, f.width) {
                (Gather::Contiguous(b), 1) => gather_fixed::<1>(rows, stride, *b, out),
                (Gather::Contiguous(b), 3) => gather_fixed::<3>(rows, stride, *b, out),
                (Gather::Contiguous(b), 4) => gather_fixed::<4>(rows, stride, *b, out),
                (Gather::RestTransposed { base, k: 3 }, _) => rest_t::<3>(rows, stride, *base, out),
                (Gather::RestTransposed { base, k: 8 }, _) => rest_t::<8>(rows, stride, *base, out),
                (Gather::RestTransposed { base, k: 15 }, _) => {
                    rest_t::<15>(rows, stride, *base, out)
                }
                (Gather::RestTransposed { base, k: 24 }, _) => {
                    rest_t::<24>(rows, stride, *base, out)
                }
                _ => gather_cols(rows, stride, &f.cols, out),
            }
            if fi == QUATS_FIELD {
                normalize_quats(out);
            }
            if fi < STANDARD_FIELDS {
                finite &= all_finite(out);
            }
        }
        finite
    }
}

#[inline(always)]
fn gather_fixed<const W: usize>(rows: &[f32], stride: usize, base: usize, out: &mut [f32]) {
    for (dst, src) in out.chunks_exact_mut(W).zip(rows.chunks_exact(stride)) {
        dst.copy_from_slice(&src[base..base + W]);
    }
}

#[inline(always)]
fn rest_t<const K: usize>(rows: &[f32], stride: usize, base: usize, out: &mut [f32]) {
    for (dst, src) in out.chunks_exact_mut(3 * K).zip(rows.chunks_exact(stride)) {
        let s = &src[base..base + 3 * K];
        let (r, gb) = s.split_at(K);
        let (g, b) = gb.split_at(K);
        for (((d, r), g), b) in dst.chunks_exact_mut(3).zip(r).zip(g).zip(b) {
            d[0] = *r;
            d[1] = *g;
            d[2] = *b;
        }
    }
}

fn gather_cols(rows: &[f32], stride: usize, cols: &[usize], out: &mut [f32]) {
    for (dst, src) in out
        .chunks_exact_mut(cols.len())
        .zip(rows.chunks_exact(stride))
    {
        for (d, &c) in dst.iter_mut().zip(cols) {
            *d = src[c];
        }
    }
}

/// True when no value is NaN or infinite (branch-free so it vectorises).
pub fn all_finite(v: &[f32]) -> bool {
    v.iter().fold(0u32, |acc, x| {
        acc | u32::from(x.to_bits() & 0x7f80_0000 == 0x7f80_0000)
    }) == 0
}
