//! OME-Zarr stores: Isowall's own pyramids read back, stores written by other programs
//! (ome-zarr-py and zarr-python, tests/data/ome_zarr/write_foreign.py), and hostile stores:
//! a compression bomb for each codec, a chunk file larger than any chunk, bad metadata.

use glam::DVec3;
use isowall_volume::io::ome_zarr::{is_zarr, OmeZarr};
use isowall_volume::io::ome_zarr_write::{mean_level, write, PyramidOptions};
use isowall_volume::io::{load, load_within, VolumeLimit};
use isowall_volume::orientation::{PatientAxes, PatientFrame};
use isowall_volume::Volume;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::codec::api::BytesToBytesCodecTraits;
use zarrs::array::codec::{BloscCodec, BloscCompressor, BloscShuffleMode, GzipCodec, ZstdCodec};
use zarrs::array::ArrayBuilder;
use zarrs::filesystem::FilesystemStore;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/ome_zarr").join(name)
}

/// A 37 x 22 x 19 grid (odd and even sides) of a smooth field, anisotropic, off the origin,
/// oriented RAS.
fn grid() -> Volume {
    let dims = [37, 22, 19];
    let mut v = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let (x, y, z) = (i as f32, j as f32, k as f32);
                v.push((x * 0.37).sin() * 40.0 + y * 1.5 - z * 0.75 + (x * y * 0.01));
            }
        }
    }
    let axes = PatientAxes::new([DVec3::X, DVec3::Y, DVec3::Z], PatientFrame::Ras).unwrap();
    Volume::new("grid", dims, DVec3::new(0.5, 0.8, 1.25), DVec3::new(-3.0, 7.5, 100.0), v)
        .unwrap()
        .with_patient_axes(Some(axes))
}

#[test]
fn a_pyramid_isowall_writes_reads_back_level_by_level_where_design_places_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("grid.ome.zarr");
    let v = grid();
    let mut calls = Vec::new();
    let summary =
        write(&v, &out, &PyramidOptions { chunk: 8, zstd_level: 3 }, &mut |d, t| calls.push((d, t))).unwrap();
    // 37x22x19 -> 19x11x10 -> 10x6x5 -> 5x3x3 (fits one chunk of 8).
    assert_eq!(summary.levels, vec![[37, 22, 19], [19, 11, 10], [10, 6, 5], [5, 3, 3]]);
    assert_eq!(calls.last(), Some(&(summary.chunks, summary.chunks)), "the progress ends at its total");
    assert!(calls.windows(2).all(|w| w[1].0 == w[0].0 + 1), "the progress moves one chunk at a time");
    assert!(is_zarr(&out));

    let store = OmeZarr::open(&out).unwrap();
    assert_eq!(store.levels().len(), 4);
    assert_eq!(store.patient_axes(), v.patient_axes(), "the orientation is kept");
    let mut expect = v.clone();
    for (l, level) in store.levels().iter().enumerate() {
        let f = f64::from(1u32 << l);
        assert!(
            (level.spacing - v.spacing() * f).abs().max_element() < 1e-12,
            "level {l}: {:?}",
            level.spacing
        );
        // Sample 0 of level l sits at origin + (2^l - 1)/2 * s0.
        let at = v.origin() + v.spacing() * (f - 1.0) / 2.0;
        assert!((level.origin - at).abs().max_element() < 1e-9, "level {l}: {:?} != {at:?}", level.origin);
        let got = store.read_level(l, 0, &VolumeLimit::default()).unwrap();
        assert_eq!(got.dims(), expect.dims(), "level {l}");
        assert_eq!(got.data(), expect.data(), "level {l}: the samples written are read back exactly");
        expect = mean_level(&expect);
    }
    // Through the common loader: level 0 whole; with a limit under level 0, the finest that fits.
    let whole = load(&out, None).unwrap();
    assert_eq!((whole.dims(), whole.data()), (v.dims(), v.data()));
    assert_eq!(
        (whole.patient_axes(), whole.orientation()),
        (v.patient_axes(), v.patient_axes().unwrap().orientation())
    );
    let level1_bytes = 19 * 11 * 10 * 4;
    let coarse = load_within(&out, None, &VolumeLimit::new(level1_bytes, "a test's budget")).unwrap();
    assert_eq!(coarse.dims(), [19, 11, 10], "the finest level within the limit");
    let e = load_within(&out, None, &VolumeLimit::new(16, "a test's budget")).unwrap_err().to_string();
    assert!(e.contains("coarsest level") && e.contains("a test's budget"), "{e}");
    // Nothing is overwritten.
    let e = write(&v, &out, &PyramidOptions::default(), &mut |_, _| {}).unwrap_err().to_string();
    assert!(e.contains("nothing is overwritten"), "{e}");
}

#[test]
fn the_per_brick_min_max_bound_every_sample_of_their_brick() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("g.ome.zarr");
    let v = grid();
    write(&v, &out, &PyramidOptions { chunk: 8, zstd_level: 1 }, &mut |_, _| {}).unwrap();
    let store = Arc::new(FilesystemStore::new(&out).unwrap());
    let a = zarrs::array::Array::open(store, "/isowall_minmax/0").unwrap();
    let mm: Vec<f32> = a.retrieve_array_subset::<Vec<f32>>(&a.subset_all()).unwrap();
    let counts = [a.shape()[2] as usize, a.shape()[1] as usize, a.shape()[0] as usize];
    assert_eq!(counts, [5, 3, 3], "bricks of 8 cells over 36x21x18 cells");
    let d = v.dims();
    for k in 0..d[2] {
        for j in 0..d[1] {
            for i in 0..d[0] {
                // Every brick holding this sample (a shared face is in both).
                for bz in [k / 8, k.saturating_sub(1) / 8] {
                    for by in [j / 8, j.saturating_sub(1) / 8] {
                        for bx in [i / 8, i.saturating_sub(1) / 8] {
                            let (bx, by, bz) =
                                (bx.min(counts[0] - 1), by.min(counts[1] - 1), bz.min(counts[2] - 1));
                            let b = 2 * (bx + counts[0] * (by + counts[1] * bz));
                            let x = v.at(i, j, k);
                            assert!(mm[b] <= x && x <= mm[b + 1], "({i},{j},{k}) in brick ({bx},{by},{bz})");
                        }
                    }
                }
            }
        }
    }
}

/// Level 0 of the foreign stores: v(x, y, z) = x + 3y + 7z - 50 on 13 x 17 x 20, scale (x, y, z)
/// (0.5, 0.75, 2.0), translation (3, -4, 10); level 1 is every other sample.
fn check_foreign(name: &str) {
    let path = data(name);
    assert!(is_zarr(&path), "{name}");
    let store = OmeZarr::open(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(store.levels().len(), 2, "{name}");
    let l0 = &store.levels()[0];
    assert_eq!(
        (l0.dims, l0.spacing, l0.origin),
        ([13, 17, 20], DVec3::new(0.5, 0.75, 2.0), DVec3::new(3.0, -4.0, 10.0))
    );
    let v = load(&path, None).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(v.dims(), [13, 17, 20]);
    for (k, j, i) in [(0, 0, 0), (19, 16, 12), (7, 3, 11), (10, 9, 0)] {
        assert_eq!(v.at(i, j, k), (i + 3 * j + 7 * k) as f32 - 50.0, "{name}: sample ({i}, {j}, {k})");
    }
    let v1 = store.read_level(1, 0, &VolumeLimit::default()).unwrap();
    assert_eq!(v1.dims(), [7, 9, 10]);
    assert_eq!(v1.at(3, 4, 5), (6 + 3 * 8 + 7 * 10) as f32 - 50.0, "{name}: level 1 is every other sample");
    assert_eq!(store.levels()[1].spacing, DVec3::new(1.0, 1.5, 4.0));
}

#[test]
fn a_store_written_by_ome_zarr_py_on_zarr_v2_with_blosc_opens() {
    check_foreign("foreign_v04.ome.zarr");
}

#[test]
fn a_sharded_store_written_by_zarr_python_on_zarr_v3_opens() {
    check_foreign("foreign_v05.ome.zarr");
}

/// A v3 array of 4x4x4 `float32` (256 bytes a chunk) compressed by `codec`, with its chunk
/// (0,0,0) replaced by `codec`'s encoding of 64 MiB of zeros.
fn bomb_store(dir: &Path, name: &str, codec: Arc<dyn BytesToBytesCodecTraits>) -> PathBuf {
    let out = dir.join(format!("{name}.ome.zarr"));
    let v = Volume::new("b", [4, 4, 4], DVec3::ONE, DVec3::ZERO, vec![1.0; 64]).unwrap();
    write(&v, &out, &PyramidOptions { chunk: 4, zstd_level: 1 }, &mut |_, _| {}).unwrap();
    // Level 0 again, with `codec`.
    std::fs::remove_dir_all(out.join("0")).unwrap();
    let store = Arc::new(FilesystemStore::new(&out).unwrap());
    let array =
        ArrayBuilder::new(vec![4u64, 4, 4], vec![4u64, 4, 4], zarrs::array::data_type::float32(), 0.0f32)
            .bytes_to_bytes_codecs(vec![codec.clone()])
            .build(store, "/0")
            .unwrap();
    array.store_metadata().unwrap();
    let bomb = codec.encode(vec![0u8; 64 << 20].into(), &Default::default()).unwrap().into_owned();
    assert!(bomb.len() < 1 << 20, "{name}: the bomb is small");
    let chunk = out.join("0/c/0/0/0");
    std::fs::create_dir_all(chunk.parent().unwrap()).unwrap();
    std::fs::write(&chunk, bomb).unwrap();
    out
}

#[test]
fn a_bomb_chunk_of_each_codec_is_refused_at_its_shapes_size() {
    let dir = tempfile::tempdir().unwrap();
    let codecs: [(&str, Arc<dyn BytesToBytesCodecTraits>); 3] = [
        ("gzip", Arc::new(GzipCodec::new(6).unwrap())),
        ("zstd", Arc::new(ZstdCodec::new(3, false))),
        (
            "blosc",
            Arc::new(
                BloscCodec::new(
                    BloscCompressor::LZ4,
                    5.try_into().unwrap(),
                    None,
                    BloscShuffleMode::NoShuffle,
                    Some(1),
                )
                .unwrap(),
            ),
        ),
    ];
    for (name, codec) in codecs {
        let path = bomb_store(dir.path(), name, codec);
        let e = load(&path, None).unwrap_err().to_string();
        assert!(
            e.contains(&format!("a {name} chunk")) && e.contains("256 bytes its shape holds"),
            "{name}: {e}"
        );
        assert!(e.contains("array `0`"), "{name}: the error names the array: {e}");
    }
}

#[test]
fn a_chunk_file_larger_than_any_chunk_is_refused_before_it_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("big.ome.zarr");
    let v = Volume::new("b", [4, 4, 4], DVec3::ONE, DVec3::ZERO, vec![1.0; 64]).unwrap();
    write(&v, &out, &PyramidOptions { chunk: 4, zstd_level: 1 }, &mut |_, _| {}).unwrap();
    // A sparse 64 GiB file where a 256-byte chunk belongs: reading it would take all memory.
    let f = std::fs::OpenOptions::new().write(true).open(out.join("0/c/0/0/0")).unwrap();
    f.set_len(64 << 30).unwrap();
    let e = load(&out, None).unwrap_err().to_string();
    assert!(e.contains("larger than any chunk of this store may be"), "{e}");
}

#[test]
fn bad_metadata_is_refused_with_what_is_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.ome.zarr");
    write(&grid(), &out, &PyramidOptions { chunk: 16, zstd_level: 1 }, &mut |_, _| {}).unwrap();
    let meta = out.join("zarr.json");
    let good = std::fs::read_to_string(&meta).unwrap();
    for (from, to, says) in [
        ("\"name\": \"x\"", "\"name\": \"w\"", "last three axes are z, y, x"),
        ("\"path\": \"1\"", "\"path\": \"9\"", "array `9` does not open"),
        ("\"path\": \"1\"", "\"path\": \"../../elsewhere\"", "must name a folder inside the store"),
        ("\"path\": \"1\"", "\"path\": \"/1\"", "must name a folder inside the store"),
        ("\"version\": \"0.5\"", "\"version\": \"7\"", "not OME-Zarr 0.4 or 0.5"),
    ] {
        assert!(good.contains(from), "{from}");
        std::fs::write(&meta, good.replacen(from, to, 1)).unwrap();
        let e = OmeZarr::open(&out).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains(says) && e.contains("m.ome.zarr"), "{from} -> {to}: {e}");
    }
    // A chunk too large to decode at once, whatever the array's size.
    let level0 = out.join("0/zarr.json");
    let good0 = std::fs::read_to_string(&level0).unwrap();
    let huge = good0.replacen(
        "\"chunk_shape\": [\n        16,\n        16,\n        16\n      ]",
        "\"chunk_shape\": [100000, 100000, 100000]",
        1,
    );
    assert_ne!(huge, good0, "the chunk shape was found in {good0}");
    std::fs::write(&meta, &good).unwrap();
    std::fs::write(&level0, huge).unwrap();
    let e = OmeZarr::open(&out).err().map(|e| e.to_string()).unwrap_or_default();
    assert!(e.contains("a chunk of 1000000000000000 samples is over"), "{e}");
    // A metadata document over the limit is not read.
    let f = std::fs::OpenOptions::new().write(true).open(&meta).unwrap();
    f.set_len(1 << 30).unwrap();
    let e = OmeZarr::open(&out).err().map(|e| e.to_string()).unwrap_or_default();
    assert!(e.contains("larger than any chunk of this store may be") || e.contains("refused"), "{e}");
}

#[test]
fn a_pyramid_streamed_slice_by_slice_from_a_raw_file_equals_the_one_written_whole() {
    use isowall_volume::io::{RawSpec, VoxelType};
    use isowall_volume::VolumeSource;
    let dir = tempfile::tempdir().unwrap();
    let v = grid();
    let raw = dir.path().join("grid.raw");
    std::fs::write(&raw, v.data().iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>()).unwrap();
    let spec = RawSpec {
        dims: v.dims(),
        voxel: VoxelType::F32,
        spacing: v.spacing(),
        big_endian: false,
        header_bytes: 0,
    };
    let stream = VolumeSource::File(raw.clone()).stream(Some(&spec)).unwrap();
    assert!(stream.partial(), "a raw file is read a slice at a time");
    let streamed = dir.path().join("streamed.ome.zarr");
    let opts = PyramidOptions { chunk: 8, zstd_level: 1 };
    isowall_volume::io::ome_zarr_write::write_stream(&stream, None, &streamed, &opts, &mut |_, _| {})
        .unwrap();
    let whole = dir.path().join("whole.ome.zarr");
    let placed = Volume::new("w", v.dims(), v.spacing(), DVec3::ZERO, v.data().to_vec()).unwrap();
    write(&placed, &whole, &opts, &mut |_, _| {}).unwrap();
    let (a, b) = (OmeZarr::open(&streamed).unwrap(), OmeZarr::open(&whole).unwrap());
    assert_eq!(a.levels().len(), b.levels().len());
    for l in 0..a.levels().len() {
        assert_eq!(
            (a.levels()[l].dims, a.levels()[l].spacing, a.levels()[l].origin),
            (b.levels()[l].dims, b.levels()[l].spacing, b.levels()[l].origin)
        );
        let (x, y) = (
            a.read_level(l, 0, &VolumeLimit::default()).unwrap(),
            b.read_level(l, 0, &VolumeLimit::default()).unwrap(),
        );
        assert_eq!(x.data(), y.data(), "level {l}: streamed and whole differ");
    }
}

#[test]
fn a_truncated_shard_is_refused_not_read_past_its_end() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("cut.ome.zarr");
    copy_dir(&data("foreign_v05.ome.zarr"), &store);
    // The shard's index sits at its end: a shard of 3 bytes cannot hold it.
    std::fs::write(store.join("s0/c/0/0/0"), [1u8, 2, 3]).unwrap();
    let e = load(&store, None).unwrap_err().to_string();
    assert!(e.contains("cut.ome.zarr") && e.contains("array `s0`"), "{e}");
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), &target).unwrap();
        }
    }
}

#[test]
fn a_store_whose_level_0_is_too_large_to_read_whole_opens_at_a_coarser_level() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("huge.ome.zarr");
    write(&grid(), &out, &PyramidOptions { chunk: 16, zstd_level: 1 }, &mut |_, _| {}).unwrap();
    // Level 0 claims 4096^3 samples (2^36, over the 2^30 read whole); its chunks are absent.
    let level0 = out.join("0/zarr.json");
    let meta = std::fs::read_to_string(&level0).unwrap();
    let claimed =
        meta.replacen("\"shape\": [\n    19,\n    22,\n    37\n  ]", "\"shape\": [4096, 4096, 4096]", 1);
    assert_ne!(claimed, meta, "the shape was found in {meta}");
    std::fs::write(&level0, claimed).unwrap();
    let store = OmeZarr::open(&out).unwrap();
    assert_eq!(store.levels()[0].dims, [4096, 4096, 4096]);
    assert_eq!(store.finest_within(&VolumeLimit::new(u64::MAX, "no limit")), Some(1));
    let v = load(&out, None).unwrap();
    assert_eq!(v.dims(), [19, 11, 10], "level 1, the finest that is read whole");
    let e = store.read_level(0, 0, &VolumeLimit::new(u64::MAX, "no limit")).unwrap_err().to_string();
    assert!(e.contains("over the 1073741824 voxels read whole"), "{e}");
    // As bricks: its min/max array no longer fits the level it claims, which is said.
    let e = store.into_bricks(0).err().unwrap().to_string();
    assert!(e.contains("isowall_minmax/0") && e.contains("the level's bricks need"), "{e}");
    // A level of 32768^3 (2^45 samples) would need 64 GiB of min/max: refused before reading.
    std::fs::write(
        &level0,
        meta.replacen("\"shape\": [\n    19,\n    22,\n    37\n  ]", "\"shape\": [32768, 32768, 32768]", 1),
    )
    .unwrap();
    let e = OmeZarr::open(&out).unwrap().into_bricks(0).err().unwrap().to_string();
    assert!(e.contains("bytes of per-brick min/max, over the 268435456 read"), "{e}");
}

/// A store as a source of cache bricks: each brick is its level's samples cut out (the far edges
/// repeated), for a store `convert` wrote (bricks of its chunks, their min/max read from the
/// store and equal to the level's own) and for stores other programs wrote (bricks of the
/// default size, ranges unknown).
#[test]
fn a_store_reads_as_bricks_that_are_its_levels_cut_up() {
    use isowall_volume::brick_cache::{BrickSource, DEFAULT_BRICK_CELLS};
    use isowall_volume::BlockMinMax;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("g.ome.zarr");
    write(&grid(), &out, &PyramidOptions { chunk: 8, zstd_level: 1 }, &mut |_, _| {}).unwrap();
    let stores = [(out, Some(8)), (data("foreign_v04.ome.zarr"), None), (data("foreign_v05.ome.zarr"), None)];
    for (path, cells) in stores {
        let store = OmeZarr::open(&path).unwrap();
        let levels: Vec<Volume> = (0..store.levels().len())
            .map(|l| store.read_level(l, 0, &VolumeLimit::default()).unwrap())
            .collect();
        let bricks = store.into_bricks(0).unwrap();
        let layout = bricks.layout().clone();
        assert_eq!(layout.cells, cells.unwrap_or(DEFAULT_BRICK_CELLS), "{path:?}");
        for (l, level) in levels.iter().enumerate() {
            assert_eq!(layout.levels[l].dims, level.dims());
            for key in layout.keys(l) {
                let got = bricks.read_brick(key).unwrap();
                assert_eq!(got, layout.cut(key, level.data()), "{path:?} {key:?}");
            }
            match cells {
                Some(c) => {
                    let own = BlockMinMax::new(level, c);
                    assert_eq!(bricks.ranges(l).unwrap(), own.minmax.as_slice(), "level {l}");
                }
                None => assert!(bricks.ranges(l).is_none(), "another program's store has no ranges"),
            }
        }
    }
    let e = OmeZarr::open(&data("foreign_v05.ome.zarr")).unwrap().into_bricks(3).err().unwrap().to_string();
    assert!(e.contains("time step 3"), "{e}");
}
