//! A minimal OpenEXR encoder for what `write_exr` writes: one single-part scanline image of
//! float32 channels, ZIP-compressed (16 lines per chunk, OpenEXR's `ZIP_COMPRESSION`).
//!
//! The `exr` crate wrote these files before (2026-11-26); it deflates every chunk with miniz at
//! level 4, which made a depth frame cost about 8x its PNG. This encoder writes the same layout
//! any OpenEXR reader expects (the header attributes OpenEXR requires, channels in name order,
//! an offset table, each chunk's bytes split into two halves and delta-coded, then zlib) with
//! zlib-rs at a fast level. The decoded values are the same bits; the file bytes differ.
//!
//! Per chunk (OpenEXR's `ImfZip.cpp`): the raw chunk is, for each of its lines, for each channel
//! in name order, the line's samples as little-endian float32. Its bytes are reordered (even
//! positions first, then odd ones), each byte after the first becomes `b[i] - b[i-1] + 128`, and
//! the result is zlib-compressed; a chunk that does not shrink is stored raw instead (readers
//! tell them apart by the stored size).

/// Lines per chunk of `ZIP_COMPRESSION`.
pub(super) const LINES_PER_CHUNK: usize = 16;

/// zlib level of the chunks (zlib-rs; 2 is its fastest level that keeps the size of miniz level 4). Measured on the
/// 1M-Gaussian pair's depth frames: see docs/rendering.md, "Fifth pass".
const LEVEL: u32 = 2;

/// OpenEXR's `ZIP_COMPRESSION` code in the `compression` attribute.
const ZIP_COMPRESSION: u8 = 3;

/// OpenEXR's `FLOAT` pixel type in a channel list.
const PIXEL_FLOAT: i32 = 2;

fn attribute(out: &mut Vec<u8>, name: &str, kind: &str, value: &[u8]) {
    out.extend_from_slice(name.as_bytes());
    out.push(0);
    out.extend_from_slice(kind.as_bytes());
    out.push(0);
    let size = i32::try_from(value.len()).expect("EXR attribute under 2 GiB");
    out.extend_from_slice(&size.to_le_bytes());
    out.extend_from_slice(value);
}

fn box2i(width: u32, height: u32) -> Vec<u8> {
    let max = |v: u32| (v as i32 - 1).to_le_bytes();
    [
        0i32.to_le_bytes(),
        0i32.to_le_bytes(),
        max(width),
        max(height),
    ]
    .concat()
}

/// Magic, version and header (attributes in name order, as OpenEXR writes them).
fn header(width: u32, height: u32, names: &[&str]) -> Vec<u8> {
    let mut out = vec![0x76, 0x2f, 0x31, 0x01];
    let long_names = names.iter().any(|n| n.len() > 31);
    let version: u32 = 2 | if long_names { 0x400 } else { 0 };
    out.extend_from_slice(&version.to_le_bytes());
    let mut chlist = Vec::new();
    for name in names {
        chlist.extend_from_slice(name.as_bytes());
        chlist.push(0);
        chlist.extend_from_slice(&PIXEL_FLOAT.to_le_bytes());
        chlist.extend_from_slice(&[0, 0, 0, 0]); // pLinear and three reserved bytes
        chlist.extend_from_slice(&1i32.to_le_bytes()); // x sampling
        chlist.extend_from_slice(&1i32.to_le_bytes()); // y sampling
    }
    chlist.push(0);
    attribute(&mut out, "channels", "chlist", &chlist);
    attribute(&mut out, "compression", "compression", &[ZIP_COMPRESSION]);
    attribute(&mut out, "dataWindow", "box2i", &box2i(width, height));
    attribute(&mut out, "displayWindow", "box2i", &box2i(width, height));
    attribute(&mut out, "lineOrder", "lineOrder", &[0]); // increasing y
    attribute(&mut out, "pixelAspectRatio", "float", &1f32.to_le_bytes());
    attribute(&mut out, "screenWindowCenter", "v2f", &[0u8; 8]);
    attribute(&mut out, "screenWindowWidth", "float", &1f32.to_le_bytes());
    out.push(0);
    out
}

/// The raw (uncompressed) bytes of lines `y0..y1`: per line, per channel in `order`, the
/// line's samples as little-endian float32.
fn raw_chunk(
    raw: &mut Vec<u8>,
    data: &[f32],
    width: usize,
    channels: usize,
    order: &[usize],
    y0: usize,
    y1: usize,
) {
    raw.clear();
    for y in y0..y1 {
        let line = &data[y * width * channels..(y + 1) * width * channels];
        if channels == 1 {
            raw.extend(line.iter().flat_map(|v| v.to_le_bytes()));
        } else {
            for &c in order {
                raw.extend(
                    line.iter()
                        .skip(c)
                        .step_by(channels)
                        .flat_map(|v| v.to_le_bytes()),
                );
            }
        }
    }
}

/// ZIP's predictor input: the even-position bytes, then the odd ones, each byte after the first
/// replaced by its difference to the previous one plus 128 (wrapping).
fn split_and_predict(raw: &[u8], out: &mut Vec<u8>) {
    out.clear();
    out.extend(raw.iter().step_by(2));
    out.extend(raw.iter().skip(1).step_by(2));
    let mut prev = out.first().copied().unwrap_or(0);
    for b in out.iter_mut().skip(1) {
        let cur = *b;
        *b = cur.wrapping_sub(prev).wrapping_add(128);
        prev = cur;
    }
}

/// zlib-compress `input` into `out` (cleared first) with a reused compressor.
fn deflate(z: &mut flate2::Compress, input: &[u8], out: &mut Vec<u8>) {
    z.reset();
    out.clear();
    // deflate's worst case is a few bytes per 16 kB over the input; a chunk that grows is
    // stored raw anyway, so stopping at the input's size plus a margin loses nothing.
    out.reserve(input.len() + input.len() / 8 + 64);
    let status = z
        .compress_vec(input, out, flate2::FlushCompress::Finish)
        .expect("in-memory zlib compression does not fail");
    if status != flate2::Status::StreamEnd {
        // out of room: the chunk would be larger than raw; make sure it is stored raw
        out.resize(input.len() + 1, 0);
    }
}

/// Encode a float32 image of `names.len()` interleaved channels (`data` row-major, `width` x
/// `height` x channels) as a ZIP-compressed scanline OpenEXR file.
pub(super) fn encode(width: u32, height: u32, names: &[String], data: &[f32]) -> Vec<u8> {
    let (w, h, channels) = (width as usize, height as usize, names.len());
    debug_assert_eq!(data.len(), w * h * channels);
    let mut order: Vec<usize> = (0..channels).collect();
    order.sort_by(|&a, &b| names[a].as_bytes().cmp(names[b].as_bytes()));
    let sorted: Vec<&str> = order.iter().map(|&c| names[c].as_str()).collect();
    let mut out = header(width, height, &sorted);
    let chunks = h.div_ceil(LINES_PER_CHUNK);
    let table = out.len();
    out.resize(table + 8 * chunks, 0);
    let mut z = flate2::Compress::new(flate2::Compression::new(LEVEL), true);
    let (mut raw, mut split, mut packed) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..chunks {
        let y0 = i * LINES_PER_CHUNK;
        let y1 = (y0 + LINES_PER_CHUNK).min(h);
        raw_chunk(&mut raw, data, w, channels, &order, y0, y1);
        split_and_predict(&raw, &mut split);
        deflate(&mut z, &split, &mut packed);
        let body: &[u8] = if packed.len() < raw.len() {
            &packed
        } else {
            &raw
        };
        let offset = out.len() as u64;
        out[table + 8 * i..table + 8 * i + 8].copy_from_slice(&offset.to_le_bytes());
        out.extend_from_slice(&(y0 as i32).to_le_bytes());
        let size = i32::try_from(body.len()).expect("an EXR chunk under 2 GiB");
        out.extend_from_slice(&size.to_le_bytes());
        out.extend_from_slice(body);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn predictor_matches_openexr_reference_bytes() {
        // OpenEXR's reference: t1 = even bytes, t2 = odd bytes; p = t[i] - t[i-1] + 128
        let raw = [10u8, 200, 11, 201, 13, 199, 250];
        let mut out = Vec::new();
        split_and_predict(&raw, &mut out);
        let t = [10u8, 11, 13, 250, 200, 201, 199];
        let mut want = vec![t[0]];
        for i in 1..t.len() {
            want.push(t[i].wrapping_sub(t[i - 1]).wrapping_add(128));
        }
        assert_eq!(out, want);
    }

    #[test]
    fn chunks_that_do_not_shrink_are_stored_raw() {
        let (w, h) = (50usize, 35usize); // 3 chunks, the last one of 3 lines
        let noise: Vec<f32> = (0..w * h)
            .map(|i| f32::from_bits((i as u32).wrapping_mul(2_654_435_761) ^ 0x5bd1_e995))
            .collect();
        let names = vec!["Y".to_string()];
        let file = encode(w as u32, h as u32, &names, &noise);
        let head = header(w as u32, h as u32, &["Y"]).len();
        // header, 3 offsets, then per chunk its y, its size and its raw little-endian samples
        assert_eq!(file.len(), head + 3 * 8 + 3 * 8 + w * h * 4);
        let first = head + 3 * 8;
        assert_eq!(file[first..first + 4], 0i32.to_le_bytes());
        assert_eq!(
            file[first + 4..first + 8],
            ((16 * w * 4) as i32).to_le_bytes()
        );
        assert_eq!(file[first + 8..first + 12], noise[0].to_le_bytes());
    }

    #[test]
    fn channels_are_laid_out_in_name_order_per_line() {
        let names: Vec<String> = ["R", "G", "B", "A"].map(String::from).to_vec();
        let order = [3usize, 2, 1, 0]; // A, B, G, R
        let data: Vec<f32> = (0..2 * 4).map(|v| v as f32).collect(); // 2 pixels, RGBA
        let mut raw = Vec::new();
        raw_chunk(&mut raw, &data, 2, names.len(), &order, 0, 1);
        let floats: Vec<f32> = raw
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        assert_eq!(floats, [3.0, 7.0, 2.0, 6.0, 1.0, 5.0, 0.0, 4.0]);
    }
}
