use super::*;

fn splat(depth: f32, x: f32, y: f32) -> Splat {
    Splat {
        xy: [x, y],
        depth,
        radius: [1.0, 1.0],
        ..Default::default()
    }
}

#[test]
fn sort_is_front_to_back_and_stable_on_ties() {
    let s: Vec<Splat> = [3.0, 1.0, 2.0, 1.0, 1e-3, 7e5]
        .iter()
        .enumerate()
        .map(|(i, &d)| splat(d, i as f32, 0.0))
        .collect();
    let sorted = sort_by_depth(&[s]);
    let order: Vec<f32> = sorted.iter().map(|s| s.xy[0]).collect();
    assert_eq!(order, [4.0, 1.0, 3.0, 2.0, 0.0, 5.0]);
}

#[test]
fn sort_matches_a_stable_sort_across_chunks_and_depth_scales() {
    // three projection chunks, depths from one narrow range (digits shared by every key
    // skip their pass) and from a wide one, with many ties
    let mut h = 7u64;
    let mut next = || {
        h = h.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
        (h >> 33) as u32
    };
    for wide in [false, true] {
        let parts: Vec<Vec<Splat>> = [5000, 0, 3000]
            .iter()
            .map(|&n| {
                (0..n)
                    .map(|_| {
                        let d = if wide {
                            f32::from_bits(0x3000_0000 + next() % 0x1800_0000)
                        } else {
                            2.0 + (next() % 64) as f32 / 64.0
                        };
                        splat(d, next() as f32, 0.0)
                    })
                    .collect()
            })
            .collect();
        let mut want: Vec<(u32, usize, usize)> = Vec::new();
        for (c, p) in parts.iter().enumerate() {
            want.extend(p.iter().enumerate().map(|(j, s)| (s.depth.to_bits(), c, j)));
        }
        want.sort(); // (depth, chunk, position): depth order, ties by Gaussian index
        let got = sort_by_depth(&parts);
        assert_eq!(got.len(), want.len());
        for (g, &(_, c, j)) in got.iter().zip(&want) {
            assert_eq!(g, &parts[c][j]);
        }
    }
}

/// `sorted_keys` of `parts` under pools of 1, 2 and 3 threads, each against the sort of
/// (depth bits, payload).
fn check_keys(parts: &[Vec<Splat>]) {
    let mut want: Vec<(u32, u32)> = Vec::new();
    for (c, p) in parts.iter().enumerate() {
        let base = (c as u32) << PROJECT_CHUNK_BITS;
        want.extend(
            p.iter()
                .enumerate()
                .map(|(j, s)| (s.depth.to_bits(), base | j as u32)),
        );
    }
    want.sort_by_key(|&(d, _)| d); // stable: ties keep payload order
    for threads in 1..=3 {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        // reused buffers holding another frame's keys
        let (mut keys, mut tmp) = (vec![(7, 7); 5], vec![(9, 9); 70_000]);
        pool.install(|| sorted_keys(parts, &mut keys, &mut tmp));
        assert!(keys == want, "{threads} threads, {} keys", want.len());
    }
}

#[test]
fn hybrid_radix_sort_equals_a_stable_sort_on_adversarial_depths() {
    let mut h = 11u64;
    let mut next = move || {
        h = h.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
        (h >> 33) as u32
    };
    let parts_of = |sizes: &[usize], d: &mut dyn FnMut() -> f32| -> Vec<Vec<Splat>> {
        sizes
            .iter()
            .map(|&n| (0..n).map(|_| splat(d(), 0.0, 0.0)).collect())
            .collect()
    };
    // no keys, one key
    check_keys(&[]);
    check_keys(&parts_of(&[0, 0], &mut || 1.0));
    check_keys(&parts_of(&[1], &mut || 3.5));
    // all equal (one bucket, every digit shared), in several parts
    check_keys(&parts_of(&[4000, 1, 2500], &mut || 2.25));
    // one bucket holding everything: depths within a quarter octave, many ties
    let mut one = || f32::from_bits(0x4000_0000 | (next() % 0x10_0000));
    check_keys(&parts_of(&[30_000, 7, 20_000], &mut one));
    // one huge bucket and tiny ones around it
    let mut skew = || {
        let r = next();
        if r % 100 < 97 {
            5.0 + (r % 1000) as f32 * 1e-4
        } else {
            f32::from_bits(0x3000_0000 + r % 0x1800_0000)
        }
    };
    check_keys(&parts_of(&[20_000, 0, 13_000], &mut skew));
    // many tiny buckets: depths spanning many octaves
    let mut wide = || f32::from_bits(0x0080_0000 + next() % 0x7e00_0000);
    check_keys(&parts_of(&[9000, 3000, 1], &mut wide));
    // buckets just around the comparison-sort threshold
    let mut edge = || {
        let r = next() % (3 * SMALL_BUCKET as u32);
        f32::from_bits(((1 + r / (SMALL_BUCKET as u32 + 1)) << TOP_SHIFT) | (r % 5))
    };
    check_keys(&parts_of(&[3 * SMALL_BUCKET], &mut edge));
}

#[test]
fn bins_follow_gsplat_tile_ranges() {
    // a splat at (16, 16) with radius 1 touches tiles x 0..2, y 0..2
    let s = splat(1.0, 16.0, 16.0);
    assert_eq!(tile_range(&s, 4, 4), (0, 2, 0, 2));
    let bins = TileBins::build(&[s, splat(2.0, 24.0, 8.0)], 4, 4).expect("bins");
    let list = |t: usize| bins.lists(t).flatten().copied().collect::<Vec<u32>>();
    assert_eq!(list(0), [0]);
    assert_eq!(list(1), [0, 1]);
    assert_eq!(list(2), Vec::<u32>::new());
    assert_eq!(list(5), [0]);
    assert_eq!(bins.intersections(), 4 + 1);
}

/// The gather's boxes are `tile_range` of each sorted splat, and binning from its
/// footprints gives the lists binning the splats gives, over several binning chunks and
/// with buffers reused from a larger frame; in box mode those are gsplat's lists, in exact
/// mode the same lists less some entries (the order kept).
#[test]
fn binning_from_the_gathers_footprints_gives_the_same_lists() {
    let mut next = footprint::tests::rng(11);
    let (tx, ty) = (13, 9);
    let (mut keys, mut tmp, mut sorted) = (Vec::new(), Vec::new(), Vec::new());
    let mut fp = Footprints::default();
    let mut reused = TileBins::default();
    for n in [3 * BIN_CHUNK + 77, 1000] {
        // projection chunks hold at most 1 << PROJECT_CHUNK_BITS splats
        let full = 1 << PROJECT_CHUNK_BITS;
        let mut sizes = vec![full; n / full];
        sizes.insert(1.min(sizes.len()), 0);
        sizes.push(n % full);
        let parts: Vec<Vec<Splat>> = sizes
            .iter()
            .map(|&m| {
                (0..m)
                    .map(|_| {
                        let mut s = footprint::tests::random_splat(&mut next, 200.0, 140.0);
                        s.depth = 1.0 + next() * 8.0;
                        s.radius = s.radius.map(|r| r.min(40.0));
                        s
                    })
                    .collect()
            })
            .collect();
        let mut exact_total = 0;
        for mode in [Mode::Box, Mode::Exact] {
            sort_by_depth_into(
                &parts,
                &mut keys,
                &mut tmp,
                &mut sorted,
                &mut fp,
                (tx, ty),
                mode,
            );
            assert!(sorted == sort_by_depth(&parts));
            for (s, b) in sorted.iter().zip(&fp.boxes) {
                let (x0, x1, y0, y1) = tile_range(s, tx, ty);
                assert_eq!(*b, [x0, x1, y0, y1].map(|v| v as u16));
            }
            let mut want = TileBins::default();
            want.rebuild_mode(&sorted, tx, ty, mode).expect("bins");
            reused.rebuild_from_footprints(&fp, tx, ty).expect("bins");
            assert_eq!(reused.n_chunks(), want.n_chunks());
            assert_eq!(reused.intersections(), want.intersections());
            let boxed = TileBins::build(&sorted, tx, ty).expect("bins");
            assert!(boxed.intersections() > n as u64);
            for t in 0..(tx * ty) as usize {
                let list = |b: &TileBins| b.lists(t).flatten().copied().collect::<Vec<u32>>();
                assert_eq!(list(&reused), list(&want), "tile {t}");
                let (got, all) = (list(&want), list(&boxed));
                if mode == Mode::Box {
                    assert_eq!(got, all, "tile {t}");
                } else {
                    // a subsequence of gsplat's list
                    let mut it = all.iter();
                    assert!(got.iter().all(|g| it.any(|a| a == g)), "tile {t}");
                }
            }
            if mode == Mode::Exact {
                exact_total = want.intersections();
                assert!(exact_total < boxed.intersections());
            }
        }
        assert!(exact_total > 0);
    }
}
