//! Depth sort and tile binning (SPEC §4 step 6).
//!
//! The visible splats are sorted once, front to back, by a stable LSD radix sort on the bits of
//! their (positive) depth, so ties keep Gaussian-index order, exactly what gsplat's stable radix
//! sort of (tile, depth bits) keys gives. The sorted array is then cut into fixed-size chunks;
//! each chunk buckets its splats by tile (a counting sort, which keeps the depth order). A tile's
//! list is the concatenation of its buckets over the chunks in order: front to back, ties by
//! index, and independent of the thread count.
use std::mem::MaybeUninit;

use rayon::prelude::*;

use super::footprint::{self, ChunkFootprints, Isa, Mode};
use super::project::{Splat, PROJECT_CHUNK_BITS};
use crate::error::{Error, Result};

/// Tile side in pixels.
pub const TILE: u32 = 16;
/// Sorted splats per binning work unit.
const BIN_CHUNK: usize = 16384;
const RADIX_BITS: u32 = 11;
const RADIX: usize = 1 << RADIX_BITS;

/// Sort splats front to back by depth; equal depths keep Gaussian-index order. `parts` are the
/// projection chunks in order (chunk c, local position j: payload c << PROJECT_CHUNK_BITS | j,
/// which orders like the Gaussian index), so no concatenated copy is needed.
#[cfg(test)]
pub(crate) fn sort_by_depth(parts: &[Vec<Splat>]) -> Vec<Splat> {
    let (mut keys, mut tmp, mut sorted) = (Vec::new(), Vec::new(), Vec::new());
    let mut fp = Footprints::default();
    sort_by_depth_into(
        parts,
        &mut keys,
        &mut tmp,
        &mut sorted,
        &mut fp,
        (1, 1),
        Mode::Box,
    );
    sorted
}

/// The sorted splats' tile footprints, as the gather writes them for binning: each splat's
/// box [x0, x1, y0, y1] (gsplat's tiles, [`tile_range`]) and the tiles of its box rows that
/// the kernels' row test may reach ([`footprint`]; the whole box in [`Mode::Box`]): a tile
/// mask per splat (tile (x0 + i, y0 + j) in bit 16 j + i), or [`footprint::TALL`] and each
/// row's column range [tx0, tx1) in its binning chunk's `tall` list (splat by splat, row by
/// row).
#[derive(Default)]
pub(crate) struct Footprints {
    pub(crate) boxes: Vec<[u16; 4]>,
    pub(crate) masks: Vec<u64>,
    pub(crate) tall: Vec<Vec<[u16; 2]>>,
}

impl Footprints {
    /// Bytes of capacity held.
    pub(crate) fn capacity_bytes(&self) -> usize {
        (self.boxes.capacity() + self.masks.capacity()) * 8
            + self.tall.iter().map(|r| r.capacity() * 4).sum::<usize>()
    }
}

/// Sorted splats gathered ahead of the one being copied (the gather reads splats at random).
const PREFETCH_AHEAD: usize = 16;

/// [`sort_by_depth`] into reused buffers (`keys` and `tmp` are scratch), also writing the
/// sorted splats' [`Footprints`] for a `tiles.0` x `tiles.1` grid (as
/// [`TileBins::rebuild_from_footprints`] takes them): the gather has each splat at hand, so
/// binning need not read the sorted splats again. A renderer keeps the buffers from frame to
/// frame, so a frame writes into memory already mapped.
pub(crate) fn sort_by_depth_into(
    parts: &[Vec<Splat>],
    keys: &mut Vec<(u32, u32)>,
    tmp: &mut Vec<(u32, u32)>,
    sorted: &mut Vec<Splat>,
    fp: &mut Footprints,
    tiles: (u32, u32),
    mode: Mode,
) {
    sorted_keys(parts, keys, tmp);
    let n = keys.len();
    sorted.clear();
    sorted.reserve(n);
    let (boxes, masks) = (&mut fp.boxes, &mut fp.masks);
    boxes.clear();
    boxes.reserve(n);
    masks.clear();
    masks.reserve(n);
    fp.tall.resize_with(n.div_ceil(BIN_CHUNK), Vec::new);
    let isa = Isa::detect();
    sorted.spare_capacity_mut()[..n]
        .par_chunks_mut(BIN_CHUNK)
        .zip(boxes.spare_capacity_mut()[..n].par_chunks_mut(BIN_CHUNK))
        .zip(masks.spare_capacity_mut()[..n].par_chunks_mut(BIN_CHUNK))
        .zip(fp.tall.par_iter_mut())
        .zip(keys.par_chunks(BIN_CHUNK))
        .for_each(|((((dst, bdst), mdst), tall), k)| {
            tall.clear();
            gather_chunk(isa, parts, k, dst, bdst, mdst, tall, tiles, mode);
        });
    // SAFETY: the chunks above cover [0, n) of the three buffers' spare capacity (reserved
    // above), and every element of every chunk was written.
    unsafe {
        sorted.set_len(n);
        boxes.set_len(n);
        masks.set_len(n);
    }
}

footprint::per_isa! {
    /// One binning chunk of the gather: the splats of keys `k` into `dst`, their boxes and
    /// tile masks into `boxes` and `masks`, tall ones' rows appended to `tall`, a group of
    /// [`footprint::GROUP`] at a time.
    #[allow(clippy::too_many_arguments)]
    fn gather_chunk(
        parts: &[Vec<Splat>],
        k: &[(u32, u32)],
        dst: &mut [MaybeUninit<Splat>],
        boxes: &mut [MaybeUninit<[u16; 4]>],
        masks: &mut [MaybeUninit<u64>],
        tall: &mut Vec<[u16; 2]>,
        tiles: (u32, u32),
        mode: Mode,
    ) => gather_chunk_impl
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn gather_chunk_impl(
    parts: &[Vec<Splat>],
    k: &[(u32, u32)],
    dst: &mut [MaybeUninit<Splat>],
    boxes: &mut [MaybeUninit<[u16; 4]>],
    masks: &mut [MaybeUninit<u64>],
    tall: &mut Vec<[u16; 2]>,
    tiles: (u32, u32),
    mode: Mode,
) {
    const G: usize = footprint::GROUP;
    let n_groups = k.len().div_ceil(G);
    let mut groups = [footprint::Group::default(), footprint::Group::default()];
    let mut dst_groups = dst.chunks_mut(G);
    if let Some(d) = dst_groups.next() {
        load_group(parts, k, 0, &mut groups[0], d);
    }
    for (g, (bg, mg)) in boxes.chunks_mut(G).zip(masks.chunks_mut(G)).enumerate() {
        // the next group's lanes are written a group ahead of their (vector) reads, so the
        // reads do not wait on the scalar stores
        let [a, c] = &mut groups;
        let (cur, next) = if g % 2 == 0 { (a, c) } else { (c, a) };
        if g + 1 < n_groups {
            if let Some(d) = dst_groups.next() {
                load_group(parts, k, g + 1, next, d);
            }
        }
        let out = footprint::Out {
            boxes: bg,
            masks: mg,
        };
        cur.emit(tiles, mode, out, tall);
    }
}

/// Copy group g's splats (keys `k[16 g..]`) into `dst` and their lanes into `group`.
#[inline(always)]
fn load_group(
    parts: &[Vec<Splat>],
    k: &[(u32, u32)],
    g: usize,
    group: &mut footprint::Group,
    dst: &mut [MaybeUninit<Splat>],
) {
    const G: usize = footprint::GROUP;
    let kg = &k[g * G..(g * G + G).min(k.len())];
    if kg.len() < G {
        *group = footprint::Group::default();
    }
    for (l, (d, &(_, p))) in dst.iter_mut().zip(kg).enumerate() {
        if let Some(&(_, ahead)) = k.get(g * G + l + PREFETCH_AHEAD) {
            crate::mem::prefetch(part_ref(parts, ahead));
        }
        let s = part_item(parts, p);
        group.set(l, &s);
        d.write(s);
    }
}

/// [`sort_by_depth`] into reused buffers, also gathering each splat's Gaussian index from
/// `ids` (laid out like `parts`): `sorted[k]` is the splat of Gaussian `sorted_ids[k]`.
pub(crate) fn sort_by_depth_with_ids(
    parts: &[Vec<Splat>],
    ids: &[Vec<u32>],
    keys: &mut Vec<(u32, u32)>,
    tmp: &mut Vec<(u32, u32)>,
    sorted: &mut Vec<Splat>,
    sorted_ids: &mut Vec<u32>,
) {
    sorted_keys(parts, keys, tmp);
    keys.par_iter()
        .with_min_len(BIN_CHUNK)
        .map(|&(_, i)| part_item(parts, i))
        .collect_into_vec(sorted);
    keys.par_iter()
        .with_min_len(BIN_CHUNK)
        .map(|&(_, i)| part_item(ids, i))
        .collect_into_vec(sorted_ids);
}

#[inline]
fn part_item<T: Copy>(parts: &[Vec<T>], payload: u32) -> T {
    *part_ref(parts, payload)
}

#[inline]
fn part_ref<T>(parts: &[Vec<T>], payload: u32) -> &T {
    &parts[(payload >> PROJECT_CHUNK_BITS) as usize]
        [(payload & ((1 << PROJECT_CHUNK_BITS) - 1)) as usize]
}

/// Bits of the most significant digit, sorted first over all keys (sign, exponent and two
/// mantissa bits: quarter octaves of depth); the 21 bits below are sorted within each of its
/// buckets.
const TOP_SHIFT: u32 = 32 - RADIX_BITS;
/// Buckets up to this size are sorted by comparison instead of radix passes (whose histograms
/// would cost more than the keys).
const SMALL_BUCKET: usize = 256;

/// The (depth bits, payload) keys of all parts sorted front to back, in `keys` (`tmp` is
/// scratch). Both buffers are reused: only their capacity survives.
///
/// A hybrid radix sort: one parallel, stable MSD scatter on the top [`RADIX_BITS`] bits (each
/// part writes its keys at the digit's global offset plus the counts of the earlier parts),
/// then each top-digit bucket, an independent range small enough to stay in cache, sorted on
/// the lower bits by stable LSD passes, the buckets in parallel. Payloads grow with the
/// Gaussian index and are unique, so the stable sort by depth is the sort by (depth, payload),
/// whatever the thread count.
fn sorted_keys(parts: &[Vec<Splat>], keys: &mut Vec<(u32, u32)>, tmp: &mut Vec<(u32, u32)>) {
    let n: usize = parts.iter().map(Vec::len).sum();
    // every key is written below (into `tmp`, then scattered into `keys`): only the part of a
    // buffer beyond what an earlier frame left needs initialising
    keys.truncate(n);
    keys.resize(n, (0, 0));
    tmp.truncate(n);
    tmp.resize(n, (0, 0));
    // each part's keys go straight to their place; (depth bits, payload), positive floats
    // ordering like their bit patterns, and each part's histogram of the top digit, in one
    // parallel pass
    let hists: Vec<Vec<u32>> = parts
        .par_iter()
        .zip(split_like(tmp, parts).into_par_iter())
        .enumerate()
        .map(|(c, (part, out))| {
            let base = (c as u32) << PROJECT_CHUNK_BITS;
            let mut hist = vec![0u32; RADIX];
            for (j, (s, k)) in part.iter().zip(out.iter_mut()).enumerate() {
                let key = s.depth.to_bits();
                hist[(key >> TOP_SHIFT) as usize] += 1;
                *k = (key, base | j as u32);
            }
            hist
        })
        .collect();
    let mut total = vec![0usize; RADIX];
    for h in &hists {
        for (a, &b) in total.iter_mut().zip(h) {
            *a += b as usize;
        }
    }
    // bucket starts: the digit's global prefix
    let mut starts = Vec::with_capacity(RADIX + 1);
    let mut sum = 0;
    for &c in &total {
        starts.push(sum);
        sum += c;
    }
    starts.push(n);
    if total.contains(&n) {
        // one bucket holds every key (depths within a quarter octave): no scatter
        std::mem::swap(keys, tmp);
    } else {
        // each part's cursor per digit: the digit's start plus the earlier parts' counts
        let mut cursors = Vec::with_capacity(parts.len());
        let mut next = starts[..RADIX].to_vec();
        for h in &hists {
            cursors.push(next.clone());
            for (a, &b) in next.iter_mut().zip(h) {
                *a += b as usize;
            }
        }
        let dst = SendPtr(keys.as_mut_ptr());
        split_like(tmp, parts)
            .into_par_iter()
            .zip(cursors.into_par_iter())
            .for_each(|(src, mut cur)| {
                let dst = &dst;
                for &k in src.iter() {
                    let c = &mut cur[(k.0 >> TOP_SHIFT) as usize];
                    // SAFETY: the parts' cursor ranges per digit are disjoint and within
                    // [0, n) (prefix sums of the counts of that digit), so every position is
                    // written by exactly one part, once.
                    unsafe { dst.0.add(*c).write(k) };
                    *c += 1;
                }
            });
    }
    // the buckets, largest first, sorted on their lower bits in parallel
    let mut buckets: Vec<(&mut [(u32, u32)], &mut [(u32, u32)])> = Vec::new();
    let (mut rk, mut rt) = (keys.as_mut_slice(), tmp.as_mut_slice());
    for w in starts.windows(2) {
        let len = w[1] - w[0];
        let (bk, tk) = rk.split_at_mut(len);
        let (bt, tt) = rt.split_at_mut(len);
        (rk, rt) = (tk, tt);
        if len > 1 {
            buckets.push((bk, bt));
        }
    }
    buckets.sort_by_key(|b| std::cmp::Reverse(b.0.len()));
    buckets
        .into_par_iter()
        .with_max_len(1)
        .for_each(|(b, scratch)| sort_low(b, scratch));
}

/// A raw pointer the scatter's parts share (they write disjoint positions).
struct SendPtr<T>(*mut T);
// SAFETY: used only for writes to disjoint positions, see the scatter in `sorted_keys`.
unsafe impl<T: Send> Send for SendPtr<T> {}
unsafe impl<T: Send> Sync for SendPtr<T> {}

/// `buf` cut into consecutive slices as long as the parts.
fn split_like<'a, T>(buf: &'a mut [T], parts: &[Vec<Splat>]) -> Vec<&'a mut [T]> {
    let mut outs = Vec::with_capacity(parts.len());
    let mut rest = buf;
    for part in parts {
        let (head, tail) = rest.split_at_mut(part.len());
        outs.push(head);
        rest = tail;
    }
    outs
}

/// Sort one top-digit bucket `b` (keys sharing their top bits, in payload order) by the lower
/// [`TOP_SHIFT`] bits, stably, in place (`scratch` is as long, its contents are overwritten):
/// LSD passes of [`RADIX_BITS`] bits, a digit all keys share skipped; small buckets by
/// comparison on (depth, payload), the same order.
fn sort_low(b: &mut [(u32, u32)], scratch: &mut [(u32, u32)]) {
    if b.len() <= SMALL_BUCKET {
        b.sort_unstable();
        return;
    }
    const PASSES: usize = TOP_SHIFT.div_ceil(RADIX_BITS) as usize;
    let mut hist = [[0u32; RADIX]; PASSES];
    for k in b.iter() {
        for (pass, h) in hist.iter_mut().enumerate() {
            h[((k.0 >> (pass as u32 * RADIX_BITS)) as usize) & (RADIX - 1)] += 1;
        }
    }
    let n = b.len() as u32;
    let (mut src, mut dst) = (&mut *b, &mut *scratch);
    let mut in_scratch = false;
    for (pass, h) in hist.iter_mut().enumerate() {
        if h.contains(&n) {
            continue;
        }
        let shift = pass as u32 * RADIX_BITS;
        let mut sum = 0;
        for c in h.iter_mut() {
            let v = *c;
            *c = sum;
            sum += v;
        }
        for k in src.iter() {
            let d = ((k.0 >> shift) as usize) & (RADIX - 1);
            dst[h[d] as usize] = *k;
            h[d] += 1;
        }
        std::mem::swap(&mut src, &mut dst);
        in_scratch = !in_scratch;
    }
    if in_scratch {
        b.copy_from_slice(scratch);
    }
}

/// Tiles touched by a splat's box: [x0, x1) x [y0, y1), as gsplat's `isect_tiles`.
#[cfg(test)]
pub(crate) fn tile_range(s: &Splat, tiles_x: u32, tiles_y: u32) -> (u32, u32, u32, u32) {
    let t = TILE as f32;
    // clamping to [0, n] first lets floor be a truncation and ceil a truncation plus one
    let floor = |v: f32, n: u32| v.clamp(0.0, n as f32) as u32;
    let ceil = |v: f32, n: u32| {
        let c = v.clamp(0.0, n as f32);
        let i = c as u32;
        i + u32::from((i as f32) < c)
    };
    (
        floor(s.xy[0] / t - s.radius[0] / t, tiles_x),
        ceil(s.xy[0] / t + s.radius[0] / t, tiles_x),
        floor(s.xy[1] / t - s.radius[1] / t, tiles_y),
        ceil(s.xy[1] / t + s.radius[1] / t, tiles_y),
    )
}

// tile coordinates of a valid camera fit the u16 of the boxes and row ranges
const _: () = assert!(crate::camera::MAX_IMAGE_SIDE.div_ceil(TILE) <= u16::MAX as u32);

#[derive(Default)]
struct BinChunk {
    /// n_tiles + 1 offsets into `items`.
    offsets: Vec<u32>,
    /// Positions in the sorted splat array.
    items: Vec<u32>,
    /// The filling pass's next position per tile (kept to reuse its memory).
    cursor: Vec<u32>,
    /// The splats' footprints when [`TileBins::rebuild`] computes them, so the filling pass
    /// reads those instead of the splats again.
    fp: ChunkFootprints,
}

/// Call `f(t)` for each tile t the footprint of a splat with box `b` and tile mask `mask`
/// keeps (row by row, left to right), for a grid `tiles_x` tiles wide; a [`footprint::TALL`]
/// splat's row ranges are next in `tall` from `*k` on. Returns the number of tiles.
#[inline(always)]
fn for_tiles(
    b: [u16; 4],
    mask: u64,
    tall: &[[u16; 2]],
    k: &mut usize,
    tiles_x: u32,
    mut f: impl FnMut(usize),
) -> u64 {
    let [x0, _, y0, y1] = b.map(u32::from);
    if mask == footprint::TALL {
        let mut n = 0;
        for (ty, r) in (y0..y1).zip(&tall[*k..]) {
            let row = (ty * tiles_x) as usize;
            for tx in r[0]..r[1] {
                f(row + tx as usize);
            }
            n += u64::from(r[1] - r[0]);
        }
        *k += (y1 - y0) as usize;
        n
    } else {
        // one loop over the set bits: its exit is the only unpredictable branch of a splat
        let base = (y0 * tiles_x + x0) as usize;
        let mut m = mask;
        while m != 0 {
            let bit = m.trailing_zeros();
            f(base + ((bit >> 4) * tiles_x + (bit & 15)) as usize);
            m &= m - 1;
        }
        u64::from(mask.count_ones())
    }
}

impl BinChunk {
    /// Bucket the sorted splats `base..base + boxes.len()`, whose footprints are `boxes`,
    /// `masks` and `tall` (see [`Footprints`]), by tile (a counting sort, so each bucket keeps
    /// the depth order).
    fn fill(
        &mut self,
        base: usize,
        (boxes, masks, tall): (&[[u16; 4]], &[u64], &[[u16; 2]]),
        tiles_x: u32,
        tiles_y: u32,
    ) -> Result<()> {
        let n_tiles = (tiles_x * tiles_y) as usize;
        // counts per tile in offsets[1..], then their exclusive prefix sums
        let offsets = &mut self.offsets;
        offsets.clear();
        offsets.resize(n_tiles + 1, 0);
        let mut total = 0u64;
        let mut k = 0;
        for (&b, &mask) in boxes.iter().zip(masks) {
            total += for_tiles(b, mask, tall, &mut k, tiles_x, |t| offsets[t + 1] += 1);
            if total > u32::MAX as u64 {
                return Err(Error::InvalidArgument(format!(
                    "too many Gaussian-tile intersections (over {}): Gaussians cover \
                     unreasonably large screen areas",
                    u32::MAX
                )));
            }
        }
        for t in 0..n_tiles {
            offsets[t + 1] += offsets[t];
        }
        self.cursor.clear();
        self.cursor.extend_from_slice(&offsets[..n_tiles]);
        let cursor = &mut self.cursor[..];
        // the zero-fill is not needed for the values (every entry is written below) but it
        // pays: it brings the chunk's list into cache sequentially, so the scattered writes
        // below hit it (writing into the reserved memory directly made garden's bin stage 10%
        // slower, 1 thread, 6 interleaved processes each)
        let items = &mut self.items;
        items.clear();
        items.resize(total as usize, 0);
        let mut k = 0;
        for (j, (&b, &mask)) in boxes.iter().zip(masks).enumerate() {
            let pos = (base + j) as u32;
            for_tiles(b, mask, tall, &mut k, tiles_x, |t| {
                let cur = &mut cursor[t];
                items[*cur as usize] = pos;
                *cur += 1;
            });
        }
        Ok(())
    }
}

/// Per-tile lists of sorted splat positions.
#[derive(Default)]
pub(crate) struct TileBins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    chunks: Vec<BinChunk>,
}

impl TileBins {
    /// Bucket depth-sorted splats by tile.
    #[cfg(test)]
    pub(crate) fn build(sorted: &[Splat], tiles_x: u32, tiles_y: u32) -> Result<Self> {
        let mut bins = TileBins::default();
        bins.rebuild_mode(sorted, tiles_x, tiles_y, Mode::Box)?;
        Ok(bins)
    }

    /// [`TileBins::build`] reusing this value's buffers (an optimiser loop bins every step),
    /// with exact binning ([`Mode::current`]).
    pub(crate) fn rebuild(&mut self, sorted: &[Splat], tiles_x: u32, tiles_y: u32) -> Result<()> {
        self.rebuild_mode(sorted, tiles_x, tiles_y, Mode::current())
    }

    /// [`TileBins::rebuild`] in the given mode.
    pub(crate) fn rebuild_mode(
        &mut self,
        sorted: &[Splat],
        tiles_x: u32,
        tiles_y: u32,
        mode: Mode,
    ) -> Result<()> {
        self.tiles_x = tiles_x;
        self.tiles_y = tiles_y;
        self.chunks
            .resize_with(sorted.len().div_ceil(BIN_CHUNK), BinChunk::default);
        let isa = Isa::detect();
        self.chunks
            .par_iter_mut()
            .zip(sorted.par_chunks(BIN_CHUNK))
            .enumerate()
            .try_for_each(|(c, (chunk, part))| {
                let mut fp = std::mem::take(&mut chunk.fp);
                footprint::of_splats(isa, part, (tiles_x, tiles_y), mode, &mut fp);
                let r = chunk.fill(
                    c * BIN_CHUNK,
                    (&fp.boxes, &fp.masks, &fp.tall),
                    tiles_x,
                    tiles_y,
                );
                chunk.fp = fp;
                r
            })
    }

    /// [`TileBins::rebuild`] from the sorted splats' footprints (as [`sort_by_depth_into`]
    /// writes them): the same lists without reading the splats.
    pub(crate) fn rebuild_from_footprints(
        &mut self,
        fp: &Footprints,
        tiles_x: u32,
        tiles_y: u32,
    ) -> Result<()> {
        self.tiles_x = tiles_x;
        self.tiles_y = tiles_y;
        self.chunks
            .resize_with(fp.boxes.len().div_ceil(BIN_CHUNK), BinChunk::default);
        self.chunks
            .par_iter_mut()
            .zip(fp.boxes.par_chunks(BIN_CHUNK))
            .zip(fp.masks.par_chunks(BIN_CHUNK))
            .zip(fp.tall.par_iter())
            .enumerate()
            .try_for_each(|(c, (((chunk, boxes), masks), tall))| {
                chunk.fill(c * BIN_CHUNK, (boxes, masks, tall), tiles_x, tiles_y)
            })
    }

    /// Sorted splats per binning chunk: splat p is binned by chunk p / BIN_CHUNK.
    pub(crate) const CHUNK: usize = BIN_CHUNK;

    /// Number of binning chunks.
    pub(crate) fn n_chunks(&self) -> usize {
        self.chunks.len()
    }

    /// Chunk c's entries before tile t's (its list is entries [start(c, t), start(c, t + 1))).
    #[inline]
    pub(crate) fn start(&self, c: usize, t: usize) -> u32 {
        self.chunks[c].offsets[t]
    }

    /// Chunk c's entries of tiles [t0, t1): those tiles' slices of their lists, one after the
    /// other (tile order).
    #[inline]
    pub(crate) fn chunk_items(&self, c: usize, t0: usize, t1: usize) -> &[u32] {
        let ch = &self.chunks[c];
        &ch.items[ch.offsets[t0] as usize..ch.offsets[t1] as usize]
    }

    /// Number of entries in tile `t`'s list.
    #[inline]
    pub(crate) fn tile_len(&self, t: usize) -> usize {
        self.chunks
            .iter()
            .map(|c| (c.offsets[t + 1] - c.offsets[t]) as usize)
            .sum()
    }

    /// The front-to-back list of tile `t`, as consecutive slices of sorted-splat positions.
    #[inline]
    pub(crate) fn lists(&self, t: usize) -> impl Iterator<Item = &[u32]> + '_ {
        self.chunks
            .iter()
            .map(move |c| &c.items[c.offsets[t] as usize..c.offsets[t + 1] as usize])
    }

    /// Bytes of every buffer (capacities), the boxes and row ranges included.
    pub(crate) fn capacity_bytes(&self) -> usize {
        self.bytes()
            + self
                .chunks
                .iter()
                .map(|c| {
                    (c.fp.boxes.capacity() + c.fp.masks.capacity()) * 8 + c.fp.tall.capacity() * 4
                })
                .sum::<usize>()
    }

    /// Bytes of the lists (capacities).
    pub(crate) fn bytes(&self) -> usize {
        self.chunks
            .iter()
            .map(|c| (c.offsets.capacity() + c.items.capacity() + c.cursor.capacity()) * 4)
            .sum()
    }

    /// Total Gaussian-tile intersections.
    pub(crate) fn intersections(&self) -> u64 {
        self.chunks.iter().map(|c| c.items.len() as u64).sum()
    }
}

#[cfg(test)]
mod tests;
