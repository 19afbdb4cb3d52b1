//! Rendering natives: `_render` (S scenes x F cameras), `_project` (one view, for tests and
//! inspection) and the PNG / EXR writers. The Python API lives in `morphgs/rendering.py`.
use std::path::PathBuf;

use numpy::ndarray::{Array1, Array2};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray4, PyArray5, PyArrayMethods, PyReadonlyArray1,
    PyReadonlyArray2, PyReadonlyArray3, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use splat_core::camera::Camera;
use splat_core::image_out::{self, Frame};
use splat_core::raster::caps::{self, Caps};
use splat_core::raster::{self, RenderOptions, RenderStats};

use crate::errors::detach;
use crate::pool;
use crate::scene::{PyGaussianScene, SceneBorrow};

/// The row-major data of a C-contiguous array (a clear ValueError naming `name` otherwise).
pub(crate) fn slice_of<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    a: &'a numpy::PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a [T]> {
    // as_slice also accepts Fortran order, whose memory order is not the row-major layout
    if !a.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "{name} must be C-contiguous"
        )));
    }
    a.as_slice()
        .map_err(|_| PyValueError::new_err(format!("{name} must be C-contiguous")))
}

pub(crate) fn cameras_from(
    w2c: &PyReadonlyArray3<'_, f64>,
    k: &PyReadonlyArray3<'_, f64>,
    width: u32,
    height: u32,
    near: f64,
    far: f64,
) -> PyResult<Vec<Camera>> {
    let (ws, ks) = (w2c.shape(), k.shape());
    if ws[1..] != [4, 4] || ks[1..] != [3, 3] || ws[0] != ks[0] {
        return Err(PyValueError::new_err(format!(
            "world_to_camera must be (F,4,4) and K (F,3,3), got {ws:?} and {ks:?}"
        )));
    }
    let (w, kk) = (slice_of(w2c, "world_to_camera")?, slice_of(k, "K")?);
    (0..ws[0])
        .map(|f| {
            Camera::from_matrices(
                &w[f * 16..f * 16 + 16],
                &kk[f * 9..f * 9 + 9],
                width,
                height,
                near,
                far,
            )
            .map_err(|e| crate::errors::CoreError(e).into())
        })
        .collect()
}

/// The blend kernel: the best the CPU has, or a lower one named by `MORPHGS_SIMD` (`avx512`,
/// `avx2`, `scalar`; for benchmarks and for checking a result on another kernel).
pub(crate) fn simd_from_env() -> PyResult<raster::Simd> {
    match std::env::var("MORPHGS_SIMD") {
        Err(_) => Ok(raster::Simd::Auto),
        Ok(v) => raster::Simd::parse(&v).ok_or_else(|| {
            PyValueError::new_err(format!(
                "MORPHGS_SIMD={v:?} is not a blend kernel: use auto, avx512, avx2 or scalar"
            ))
        }),
    }
}

fn options(
    background: [f32; 3],
    max_alpha: f32,
    sh_degree: Option<u8>,
    antialiased: bool,
) -> PyResult<RenderOptions> {
    Ok(RenderOptions {
        background,
        max_alpha,
        sh_degree,
        antialiased,
        simd: simd_from_env()?,
        count_useful: count_useful_from_env(),
    })
}

/// Whether `MORPHGS_COUNT_USEFUL` (set and not "0") asks render to count the useful
/// evaluations (stats `useful_evaluations`; for benchmarks, it slows the blend).
fn count_useful_from_env() -> bool {
    std::env::var("MORPHGS_COUNT_USEFUL").is_ok_and(|v| !v.is_empty() && v != "0")
}

fn stats_dict<'py>(py: Python<'py>, s: &RenderStats) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("frames", s.frames)?;
    d.set_item("gaussians", s.gaussians)?;
    d.set_item("visible", s.visible)?;
    d.set_item("intersections", s.intersections)?;
    d.set_item("evaluations", s.evaluations)?;
    d.set_item("useful_evaluations", s.useful)?;
    d.set_item("project_s", s.project_s)?;
    d.set_item("sort_s", s.sort_s)?;
    d.set_item("bin_s", s.bin_s)?;
    d.set_item("blend_s", s.blend_s)?;
    d.set_item("simd", simd_from_env()?.resolve().name())?;
    d.set_item("threads", py.detach(pool::num_threads))?;
    Ok(d)
}

type RenderOut<'py> = (
    Bound<'py, PyArray5<f32>>,
    Bound<'py, PyArray4<f32>>,
    Bound<'py, PyArray4<f32>>,
    Bound<'py, PyDict>,
);

/// Render S scenes from F cameras sharing one image size, in one parallel pass (GIL released).
///
/// Returns (rgb (S,F,H,W,3), depth (S,F,H,W), alpha (S,F,H,W), stats dict), float32. With `out`
/// (three writable C-contiguous float32 arrays of those shapes) the images are written into
/// them (every value) and those arrays are returned.
#[pyfunction]
#[pyo3(signature = (scenes, world_to_camera, K, width, height, *, near = 0.01, far = 1e10,
                    background = [0.0, 0.0, 0.0], max_alpha = 0.99, sh_degree = None,
                    antialiased = false, out = None))]
#[allow(non_snake_case, clippy::too_many_arguments)]
fn _render<'py>(
    py: Python<'py>,
    scenes: &Bound<'py, PyList>,
    world_to_camera: PyReadonlyArray3<'py, f64>,
    K: PyReadonlyArray3<'py, f64>,
    width: u32,
    height: u32,
    near: f64,
    far: f64,
    background: [f32; 3],
    max_alpha: f32,
    sh_degree: Option<u8>,
    antialiased: bool,
    out: Option<OutArrays<'py>>,
) -> PyResult<RenderOut<'py>> {
    let cams = cameras_from(&world_to_camera, &K, width, height, near, far)?;
    let handles: Vec<Bound<'py, PyGaussianScene>> = scenes
        .iter()
        .map(|s| {
            s.cast_into::<PyGaussianScene>()
                .map_err(|_| PyTypeError::new_err("scenes must be a list of GaussianScene"))
        })
        .collect::<PyResult<_>>()?;
    let borrows: Vec<SceneBorrow<'py>> = handles
        .iter()
        .map(|h| h.get().borrow(py))
        .collect::<PyResult<_>>()?;
    let views = borrows
        .iter()
        .map(SceneBorrow::view)
        .collect::<PyResult<Vec<_>>>()?;
    // the popping caps a scene carries as extras (docs/artifacts.md): it renders with them
    let cap_extras = handles
        .iter()
        .map(|h| cap_extras(py, h.get()))
        .collect::<PyResult<Vec<_>>>()?;
    let mut caps = Vec::with_capacity(cap_extras.len());
    for e in &cap_extras {
        caps.push(match e {
            Some([x, y, z, h]) => Some(Caps::of(
                slice_of(x, "popping_x")?,
                slice_of(y, "popping_y")?,
                slice_of(z, "popping_z")?,
                slice_of(h, "popping_h")?,
            )),
            None => None,
        });
    }
    let caps: &[Option<Caps<'_>>] = if caps.iter().any(Option::is_some) {
        &caps
    } else {
        &[]
    };
    let opts = options(background, max_alpha, sh_degree, antialiased)?;
    let (s, f, h, w) = (views.len(), cams.len(), height as usize, width as usize);
    if let Some((rgb, depth, alpha)) = out {
        let stats = {
            let shape = [s, f, h, w];
            let mut rgb_w = writable(&rgb, "out rgb", &[s, f, h, w, 3])?;
            let mut depth_w = writable(&depth, "out depth", &shape)?;
            let mut alpha_w = writable(&alpha, "out alpha", &shape)?;
            let slices = (
                rgb_w.as_slice_mut(),
                depth_w.as_slice_mut(),
                alpha_w.as_slice_mut(),
            );
            let (Ok(rgb_s), Ok(depth_s), Ok(alpha_s)) = slices else {
                return Err(PyValueError::new_err("out arrays must be C-contiguous"));
            };
            detach(py, || {
                raster::render_batch_into_caps(&views, caps, &cams, &opts, rgb_s, depth_s, alpha_s)
            })?
        };
        let rgb = rgb.cast_into::<PyArray5<f32>>()?;
        let depth = depth.cast_into::<PyArray4<f32>>()?;
        let alpha = alpha.cast_into::<PyArray4<f32>>()?;
        return Ok((rgb, depth, alpha, stats_dict(py, &stats)?));
    }
    // the images go into buffers of released outputs where there are some (every value is
    // written), and the arrays hand their buffers back when Python releases them
    let n = s * f * h * w;
    let pool = &splat_core::mem::OUTPUTS;
    let (mut rgb, mut depth, mut alpha) = (pool.take(n * 3), pool.take(n), pool.take(n));
    let stats = detach(py, || {
        raster::render_batch_into_caps(&views, caps, &cams, &opts, &mut rgb, &mut depth, &mut alpha)
    });
    let stats = match stats {
        Ok(st) => st,
        Err(e) => {
            for b in [rgb, depth, alpha] {
                pool.give(b);
            }
            return Err(e);
        }
    };
    let shape = [s, f, h, w];
    Ok((
        pooled_array(py, rgb, numpy::ndarray::Ix5(s, f, h, w, 3))?,
        pooled_array(py, depth, numpy::ndarray::Dim(shape))?,
        pooled_array(py, alpha, numpy::ndarray::Dim(shape))?,
        stats_dict(py, &stats)?,
    ))
}

/// A scene's popping caps: its extras named [`caps::EXTRAS`], all four, or None without any
/// (a ValueError naming the missing ones for some only).
fn cap_extras<'py>(
    py: Python<'py>,
    scene: &PyGaussianScene,
) -> PyResult<Option<[PyReadonlyArray1<'py, f32>; 4]>> {
    let mut found: [Option<PyReadonlyArray1<'py, f32>>; 4] = Default::default();
    for (name, a) in scene.extras_readonly(py)? {
        if let Some(k) = caps::EXTRAS.iter().position(|e| *e == name) {
            found[k] = Some(a);
        }
    }
    let missing: Vec<&str> = caps::EXTRAS
        .iter()
        .zip(&found)
        .filter(|(_, a)| a.is_none())
        .map(|(n, _)| *n)
        .collect();
    match found {
        [Some(x), Some(y), Some(z), Some(h)] => Ok(Some([x, y, z, h])),
        _ if missing.len() == 4 => Ok(None),
        _ => Err(PyValueError::new_err(format!(
            "the scene carries popping caps without {} (extras {} go together)",
            missing.join(", "),
            caps::EXTRAS.join(", ")
        ))),
    }
}

/// The owner of a returned image array's memory: when Python releases the array (and every
/// view of it), its buffer goes back to [`splat_core::mem::OUTPUTS`] for the next render.
#[pyclass(frozen, module = "morphgs._core")]
struct PooledBuffer {
    data: Vec<f32>,
}

impl Drop for PooledBuffer {
    fn drop(&mut self) {
        splat_core::mem::OUTPUTS.give(std::mem::take(&mut self.data));
    }
}

/// A writable numpy array of `shape` over `data` (C order), owned by a [`PooledBuffer`].
fn pooled_array<'py, D: numpy::ndarray::Dimension>(
    py: Python<'py>,
    data: Vec<f32>,
    shape: D,
) -> PyResult<Bound<'py, numpy::PyArray<f32, D>>> {
    let owner = Bound::new(py, PooledBuffer { data })?;
    let view = numpy::ndarray::ArrayView::from_shape(shape, &owner.get().data[..])
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    // SAFETY: the array's base is `owner`, which holds `data` unchanged (a frozen class: the
    // vector is never reallocated, nor touched by Rust) until the array and all its views are
    // gone; only then does the buffer go back to the pool.
    Ok(unsafe { numpy::PyArray::borrow_from_array(&view, owner.clone().into_any()) })
}

/// `_render`'s `out`: rgb, depth and alpha arrays to render into.
type OutArrays<'py> = (
    Bound<'py, PyUntypedArray>,
    Bound<'py, PyUntypedArray>,
    Bound<'py, PyUntypedArray>,
);

/// A writable float32 view of `a`, which must have exactly `shape` and be C-contiguous (a
/// ValueError naming `name` otherwise; a TypeError for another dtype; the same array given
/// twice cannot be borrowed twice and raises too).
fn writable<'py>(
    a: &Bound<'py, PyUntypedArray>,
    name: &str,
    shape: &[usize],
) -> PyResult<numpy::PyReadwriteArrayDyn<'py, f32>> {
    let arr = a
        .cast::<numpy::PyArrayDyn<f32>>()
        .map_err(|_| PyTypeError::new_err(format!("{name} must be a float32 array")))?;
    if a.shape() != shape || !a.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "{name} must be a C-contiguous array of shape {shape:?}, got {:?}",
            a.shape()
        )));
    }
    arr.try_readwrite()
        .map_err(|e| PyValueError::new_err(format!("{name} cannot be written: {e}")))
}

/// Project every Gaussian of a scene for one camera (SPEC §4 steps 1-5), as gsplat's
/// `fully_fused_projection` reports it. Culled Gaussians have radii 0.
///
/// Returns a dict: radii (N,2) int32, means2d (N,2), depths (N,), conics (N,3),
/// opacities (N,), colors (N,3), float32.
#[pyfunction]
#[pyo3(signature = (scene, world_to_camera, K, width, height, *, near = 0.01, far = 1e10,
                    sh_degree = None, antialiased = false))]
#[allow(non_snake_case)]
fn _project<'py>(
    py: Python<'py>,
    scene: &PyGaussianScene,
    world_to_camera: PyReadonlyArray2<'py, f64>,
    K: PyReadonlyArray2<'py, f64>,
    width: u32,
    height: u32,
    near: f64,
    far: f64,
    sh_degree: Option<u8>,
    antialiased: bool,
) -> PyResult<Bound<'py, PyDict>> {
    if world_to_camera.shape() != [4, 4] || K.shape() != [3, 3] {
        return Err(PyValueError::new_err(
            "world_to_camera must be (4,4) and K (3,3)",
        ));
    }
    let cam = Camera::from_matrices(
        slice_of(&world_to_camera, "world_to_camera")?,
        slice_of(&K, "K")?,
        width,
        height,
        near,
        far,
    )
    .map_err(crate::errors::CoreError)?;
    let b = scene.borrow(py)?;
    let view = b.view()?;
    let opts = options([0.0; 3], 0.99, sh_degree, antialiased)?;
    let p = detach(py, || raster::project_all(&view, &cam, &opts))?;
    projection_dict(py, p)
}

/// gsplat's `fully_fused_projection` outputs of a [`raster::Projection`] as a dict of arrays:
/// radii (N,2) int32, means2d (N,2), depths (N,), conics (N,3), opacities (N,), colors (N,3).
pub(crate) fn projection_dict(
    py: Python<'_>,
    p: raster::Projection,
) -> PyResult<Bound<'_, PyDict>> {
    let n = p.depths.len();
    let bad = |e: numpy::ndarray::ShapeError| PyValueError::new_err(e.to_string());
    let d = PyDict::new(py);
    let radii: Bound<'_, PyArray2<i32>> = Array2::from_shape_vec((n, 2), p.radii)
        .map_err(bad)?
        .into_pyarray(py);
    d.set_item("radii", radii)?;
    d.set_item(
        "means2d",
        Array2::from_shape_vec((n, 2), p.means2d)
            .map_err(bad)?
            .into_pyarray(py),
    )?;
    let depths: Bound<'_, PyArray1<f32>> = Array1::from_vec(p.depths).into_pyarray(py);
    d.set_item("depths", depths)?;
    d.set_item(
        "conics",
        Array2::from_shape_vec((n, 3), p.conics)
            .map_err(bad)?
            .into_pyarray(py),
    )?;
    d.set_item("opacities", Array1::from_vec(p.opacities).into_pyarray(py))?;
    d.set_item(
        "colors",
        Array2::from_shape_vec((n, 3), p.colors)
            .map_err(bad)?
            .into_pyarray(py),
    )?;
    Ok(d)
}

/// (frames, height, width, channels) of an (F,H,W) or (F,H,W,C) array, or of (H,W) / (H,W,C)
/// when `batched` is false.
fn image_dims(a: &Bound<'_, PyUntypedArray>, batched: bool) -> PyResult<(usize, u32, u32, usize)> {
    let s = a.shape();
    let (f, rest) = if batched {
        match s.split_first() {
            Some((f, rest)) => (*f, rest),
            None => return Err(PyValueError::new_err("images must be (F,H,W) or (F,H,W,C)")),
        }
    } else {
        (1, s)
    };
    let (h, w, c) = match rest {
        [h, w] => (*h, *w, 1),
        [h, w, c] => (*h, *w, *c),
        _ => {
            return Err(PyValueError::new_err(format!(
                "an image must be (H,W) or (H,W,C), got shape {s:?}"
            )))
        }
    };
    let as_u32 = |v: usize| {
        u32::try_from(v).map_err(|_| PyValueError::new_err(format!("image side {v} too large")))
    };
    Ok((f, as_u32(w)?, as_u32(h)?, c))
}

fn check_paths(paths: &[PathBuf], frames: usize) -> PyResult<()> {
    if paths.len() != frames {
        return Err(PyValueError::new_err(format!(
            "{} paths for {frames} images",
            paths.len()
        )));
    }
    Ok(())
}

/// Write a uint8 image (H,W), (H,W,3) or (H,W,4) as PNG (atomically); a float32 image is
/// converted as `Render.to_uint8` does.
#[pyfunction]
fn _write_png(py: Python<'_>, path: PathBuf, image: &Bound<'_, PyUntypedArray>) -> PyResult<()> {
    _write_png_batch(py, vec![path], image, false)
}

/// Write a float32 image (H,W) or (H,W,C) as OpenEXR (atomically).
#[pyfunction]
fn _write_exr(py: Python<'_>, path: PathBuf, image: &Bound<'_, PyUntypedArray>) -> PyResult<()> {
    _write_exr_batch(py, vec![path], image, false)
}

/// Write F images (F,H,W[,C]) as PNGs, in parallel; `paths` has F entries. uint8 images are
/// written as they are; float32 colour is converted frame by frame inside the parallel writers
/// by `Render.to_uint8`'s rule, round(clip(v, 0, 1) * 255) with ties to even (the same bytes,
/// without a batch-sized uint8 copy).
#[pyfunction]
#[pyo3(signature = (paths, images, batched = true))]
fn _write_png_batch(
    py: Python<'_>,
    paths: Vec<PathBuf>,
    images: &Bound<'_, PyUntypedArray>,
    batched: bool,
) -> PyResult<()> {
    let (f, w, h, c) = image_dims(images, batched)?;
    check_paths(&paths, f)?;
    if let Ok(floats) = images.cast::<numpy::PyArrayDyn<f32>>() {
        let arr = floats.try_readonly()?;
        let frames = split_frames(paths, slice_of(&arr, "images")?, f);
        return detach(py, || image_out::write_png_batch_f32(&frames, w, h, c));
    }
    let arr = images
        .cast::<numpy::PyArrayDyn<u8>>()
        .map_err(|_| PyTypeError::new_err("PNG images must be uint8 or float32 arrays"))?
        .try_readonly()?;
    let frames = split_frames(paths, slice_of(&arr, "images")?, f);
    detach(py, || image_out::write_png_batch(&frames, w, h, c))
}

/// Write F float32 images (F,H,W[,C]) as OpenEXRs, in parallel; `paths` has F entries.
#[pyfunction]
#[pyo3(signature = (paths, images, batched = true))]
fn _write_exr_batch(
    py: Python<'_>,
    paths: Vec<PathBuf>,
    images: &Bound<'_, PyUntypedArray>,
    batched: bool,
) -> PyResult<()> {
    let (f, w, h, c) = image_dims(images, batched)?;
    check_paths(&paths, f)?;
    let arr = images
        .cast::<numpy::PyArrayDyn<f32>>()
        .map_err(|_| PyTypeError::new_err("EXR images must be float32 arrays"))?
        .try_readonly()?;
    let frames = split_frames(paths, slice_of(&arr, "images")?, f);
    detach(py, || image_out::write_exr_batch(&frames, w, h, c))
}

/// Read OpenEXR files (in parallel) as float32 arrays: (H,W) for one channel, (H,W,C) otherwise.
/// Raises SceneFormatError naming the file for a malformed one, and refuses images of more than
/// `max_values` samples before decoding them.
#[pyfunction]
#[pyo3(signature = (paths, max_values = 1usize << 30))]
fn _read_exr_batch<'py>(
    py: Python<'py>,
    paths: Vec<PathBuf>,
    max_values: usize,
) -> PyResult<Vec<Bound<'py, PyAny>>> {
    let images = detach(py, || image_out::read_exr_batch(&paths, max_values))?;
    images
        .into_iter()
        .map(|im| {
            let (h, w, c) = (im.height as usize, im.width as usize, im.channels);
            let arr = Array1::from_vec(im.data);
            Ok(if c == 1 {
                arr.into_shape_with_order((h, w))
                    .map_err(|e| PyValueError::new_err(e.to_string()))?
                    .into_pyarray(py)
                    .into_any()
            } else {
                arr.into_shape_with_order((h, w, c))
                    .map_err(|e| PyValueError::new_err(e.to_string()))?
                    .into_pyarray(py)
                    .into_any()
            })
        })
        .collect()
}

/// PNG frames as 8-bit RGB, decoded in parallel: for each path, the (rows, W, 3) uint8 array of
/// its first `max_rows` rows (all rows when None) and the file's full height. Sizes are checked
/// against `max_values` before decoding.
#[pyfunction]
#[pyo3(signature = (paths, max_rows = None, max_values = 1usize << 31))]
fn _read_png_batch<'py>(
    py: Python<'py>,
    paths: Vec<PathBuf>,
    max_rows: Option<u32>,
    max_values: usize,
) -> PyResult<Vec<(Bound<'py, PyAny>, u32)>> {
    let images = detach(py, || {
        image_out::read_png_batch(&paths, max_rows, max_values)
    })?;
    images
        .into_iter()
        .map(|im| {
            let shape = (im.rows as usize, im.width as usize, 3);
            let arr = Array1::from_vec(im.data)
                .into_shape_with_order(shape)
                .map_err(|e| PyValueError::new_err(e.to_string()))?;
            Ok((arr.into_pyarray(py).into_any(), im.height))
        })
        .collect()
}

/// One frame per path over consecutive equal parts of `data`.
fn split_frames<T>(paths: Vec<PathBuf>, data: &[T], f: usize) -> Vec<Frame<'_, T>> {
    let per = data.len() / f.max(1);
    paths
        .into_iter()
        .enumerate()
        .map(|(i, path)| Frame {
            path,
            data: &data[i * per..(i + 1) * per],
        })
        .collect()
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_render, m)?)?;
    m.add_function(wrap_pyfunction!(_project, m)?)?;
    m.add_function(wrap_pyfunction!(_write_png, m)?)?;
    m.add_function(wrap_pyfunction!(_write_exr, m)?)?;
    m.add_function(wrap_pyfunction!(_write_png_batch, m)?)?;
    m.add_function(wrap_pyfunction!(_write_exr_batch, m)?)?;
    m.add_function(wrap_pyfunction!(_read_exr_batch, m)?)?;
    m.add_function(wrap_pyfunction!(_read_png_batch, m)?)?;
    Ok(())
}
