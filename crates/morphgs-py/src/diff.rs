//! `_core.DiffRasterizer`: the differentiable rasterizer (forward with saved state, backward)
//! over stored-parameter arrays. The torch autograd op `morphgs.torch.rasterization` is built on
//! it (python/morphgs/torch/).
use std::sync::Mutex;

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use splat_core::camera::Camera;

use crate::render::slice_of;
use splat_core::raster::diff::{
    DensifyStats, DepthKind, DiffOptions, Gradients, ImageGrads, ViewGrads, Workspace,
};
use splat_core::raster::RenderOptions;
use splat_core::scene::sh_degree_for_rest;
use splat_core::SceneView;

use crate::errors::{detach, CoreError};

/// Stored parameters as borrowed NumPy arrays.
struct Params<'py> {
    means: PyReadonlyArray2<'py, f32>,
    quats: PyReadonlyArray2<'py, f32>,
    log_scales: PyReadonlyArray2<'py, f32>,
    opacity_logits: PyReadonlyArray1<'py, f32>,
    sh0: PyReadonlyArray2<'py, f32>,
    sh_rest: PyReadonlyArray3<'py, f32>,
    colors: Option<PyReadonlyArray2<'py, f32>>,
}

impl Params<'_> {
    fn view(&self) -> PyResult<SceneView<'_>> {
        let k = self.sh_rest.shape()[1];
        let degree = sh_degree_for_rest(k).ok_or_else(|| {
            PyValueError::new_err(format!(
                "sh_rest must be (N,K,3) with K = (d+1)^2 - 1 for d in 0..4, got K = {k}"
            ))
        })?;
        if self.sh_rest.shape()[2] != 3 && self.sh_rest.shape()[0] > 0 {
            return Err(PyValueError::new_err("sh_rest must be (N,K,3)"));
        }
        SceneView::new(
            slice_of(&self.means, "means")?,
            slice_of(&self.quats, "quats")?,
            slice_of(&self.log_scales, "log_scales")?,
            slice_of(&self.opacity_logits, "opacity_logits")?,
            slice_of(&self.sh0, "sh0")?,
            slice_of(&self.sh_rest, "sh_rest")?,
            degree,
        )
        .map_err(|e| CoreError(e).into())
    }

    fn colors(&self) -> PyResult<Option<&[f32]>> {
        self.colors
            .as_ref()
            .map(|c| slice_of(c, "colors"))
            .transpose()
    }
}

/// A differentiable CPU rasterizer for one camera: `forward` renders and keeps what `backward`
/// needs; `backward` returns the gradients of the stored parameters. The buffers are reused
/// from call to call. Parameters are float32 C-contiguous arrays in the stored (pre-activation)
/// layout of `GaussianScene`: means (N,3), quats (N,4), log_scales (N,3), opacity_logits (N,),
/// sh0 (N,3), sh_rest (N,K,3); `colors` (N,3), when given, replace the SH colours.
#[pyclass(name = "DiffRasterizer", module = "morphgs._core", frozen)]
pub struct PyDiffRasterizer {
    ws: Mutex<Workspace>,
}

#[pymethods]
impl PyDiffRasterizer {
    #[new]
    fn new() -> Self {
        PyDiffRasterizer {
            ws: Mutex::new(Workspace::default()),
        }
    }

    /// Render one camera and keep the state for `backward`.
    ///
    /// Args:
    ///     means, quats, log_scales, opacity_logits, sh0, sh_rest: the stored parameters.
    ///     world_to_camera: (4,4) float64; K: (3,3) float64; width, height: image size.
    ///     colors: optional (N,3) float32 colours used instead of SH.
    ///     depth: "expected" (D / max(alpha, 1e-10), as render) or "accumulated" (D).
    ///     slot_budget: most bytes of per-intersection gradient slots held at once.
    ///     absgrad: have `backward` also sum |dL/dmean2d| per pixel (means2d_abs, grad2d_abs).
    ///
    /// Returns:
    ///     (rgb (H,W,3), depth (H,W), alpha (H,W), stats dict), float32.
    ///
    /// Raises:
    ///     ValueError: bad shapes, camera or options.
    #[pyo3(signature = (means, quats, log_scales, opacity_logits, sh0, sh_rest, world_to_camera,
                        K, width, height, *, near = 0.01, far = 1e10, background = [0.0, 0.0, 0.0],
                        max_alpha = 0.99, sh_degree = None, antialiased = false, colors = None,
                        depth = "expected", slot_budget = 256usize << 20, absgrad = false))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn forward<'py>(
        &self,
        py: Python<'py>,
        means: PyReadonlyArray2<'py, f32>,
        quats: PyReadonlyArray2<'py, f32>,
        log_scales: PyReadonlyArray2<'py, f32>,
        opacity_logits: PyReadonlyArray1<'py, f32>,
        sh0: PyReadonlyArray2<'py, f32>,
        sh_rest: PyReadonlyArray3<'py, f32>,
        world_to_camera: PyReadonlyArray2<'py, f64>,
        K: PyReadonlyArray2<'py, f64>,
        width: u32,
        height: u32,
        near: f64,
        far: f64,
        background: [f32; 3],
        max_alpha: f32,
        sh_degree: Option<u8>,
        antialiased: bool,
        colors: Option<PyReadonlyArray2<'py, f32>>,
        depth: &str,
        slot_budget: usize,
        absgrad: bool,
    ) -> PyResult<(
        Bound<'py, PyArray3<f32>>,
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyDict>,
    )> {
        let p = Params {
            means,
            quats,
            log_scales,
            opacity_logits,
            sh0,
            sh_rest,
            colors,
        };
        let view = p.view()?;
        let colors = p.colors()?;
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
        .map_err(CoreError)?;
        let depth = match depth {
            "expected" => DepthKind::Expected,
            "accumulated" => DepthKind::Accumulated,
            other => {
                return Err(PyValueError::new_err(format!(
                    "depth must be \"expected\" or \"accumulated\", got {other:?}"
                )))
            }
        };
        let opts = DiffOptions {
            render: RenderOptions {
                background,
                max_alpha,
                sh_degree,
                antialiased,
                simd: crate::render::simd_from_env()?,
                count_useful: false,
            },
            depth,
            slot_budget,
            absgrad,
        };
        let npix = width as usize * height as usize;
        let (mut rgb, mut dep, mut alpha) = (vec![0.0; npix * 3], vec![0.0; npix], vec![0.0; npix]);
        let stats = detach(py, || {
            self.locked()?
                .forward(&view, &cam, &opts, colors, &mut rgb, &mut dep, &mut alpha)
        })?;
        let (h, w) = (height as usize, width as usize);
        let bad = |e: numpy::ndarray::ShapeError| PyValueError::new_err(e.to_string());
        let d = PyDict::new(py);
        d.set_item("visible", stats.visible)?;
        d.set_item("intersections", stats.intersections)?;
        d.set_item("evaluations", stats.evaluations)?;
        d.set_item("project_s", stats.project_s)?;
        d.set_item("sort_s", stats.sort_s)?;
        d.set_item("bin_s", stats.bin_s)?;
        d.set_item("blend_s", stats.blend_s)?;
        d.set_item("simd", opts.render.simd.resolve().name())?;
        Ok((
            Array3::from_shape_vec((h, w, 3), rgb)
                .map_err(bad)?
                .into_pyarray(py),
            Array2::from_shape_vec((h, w), dep)
                .map_err(bad)?
                .into_pyarray(py),
            Array2::from_shape_vec((h, w), alpha)
                .map_err(bad)?
                .into_pyarray(py),
            d,
        ))
    }

    /// Gradients of the last `forward`'s stored parameters from the image gradients.
    ///
    /// Args:
    ///     means, quats, log_scales, opacity_logits, sh0, sh_rest, colors: the forward's arrays.
    ///     v_rgb (H,W,3), v_depth (H,W), v_alpha (H,W): dL/d(images), None for zero; v_depth
    ///         refers to the depth kind the forward wrote.
    ///     view: also return this view's intermediate gradients (means2d, means2d_abs, conics,
    ///         view_colors, view_opacities, view_depths).
    ///     viewmat: also return "viewmat", dL/d(world_to_camera) (4,4) float64 (gsplat's
    ///         v_viewmats; implies `view`).
    ///     cameras_per_step: gsplat's n_cameras factor of the densification statistics.
    ///
    /// Returns:
    ///     dict of float32 arrays: means, quats, log_scales, opacity_logits, sh0, sh_rest,
    ///     scales and opacities (activated), colors (when given), background (3,), the
    ///     densification statistics grad2d, grad2d_abs, count, max_radius (N,), the view
    ///     gradients when asked, and "stats" (a dict).
    ///
    /// Raises:
    ///     ValueError: no forward yet, or arrays that do not match it.
    #[pyo3(signature = (means, quats, log_scales, opacity_logits, sh0, sh_rest, *, colors = None,
                        v_rgb = None, v_depth = None, v_alpha = None, view = false,
                        viewmat = false, cameras_per_step = 1.0))]
    #[allow(clippy::too_many_arguments)]
    fn backward<'py>(
        &self,
        py: Python<'py>,
        means: PyReadonlyArray2<'py, f32>,
        quats: PyReadonlyArray2<'py, f32>,
        log_scales: PyReadonlyArray2<'py, f32>,
        opacity_logits: PyReadonlyArray1<'py, f32>,
        sh0: PyReadonlyArray2<'py, f32>,
        sh_rest: PyReadonlyArray3<'py, f32>,
        colors: Option<PyReadonlyArray2<'py, f32>>,
        v_rgb: Option<PyReadonlyArray3<'py, f32>>,
        v_depth: Option<PyReadonlyArray2<'py, f32>>,
        v_alpha: Option<PyReadonlyArray2<'py, f32>>,
        view: bool,
        viewmat: bool,
        cameras_per_step: f32,
    ) -> PyResult<Bound<'py, PyDict>> {
        let view = view || viewmat;
        let p = Params {
            means,
            quats,
            log_scales,
            opacity_logits,
            sh0,
            sh_rest,
            colors,
        };
        let scene = p.view()?;
        let colors = p.colors()?;
        let grads = ImageGrads {
            rgb: v_rgb.as_ref().map(|a| slice_of(a, "v_rgb")).transpose()?,
            depth: v_depth
                .as_ref()
                .map(|a| slice_of(a, "v_depth"))
                .transpose()?,
            alpha: v_alpha
                .as_ref()
                .map(|a| slice_of(a, "v_alpha"))
                .transpose()?,
            skip_background: false,
        };
        let n = scene.len();
        let k = scene.sh_rest_k();
        let mut out = Gradients::default();
        out.reset(n, k, colors.is_some());
        let mut vg = ViewGrads {
            viewmat: viewmat.then_some([0.0; 16]),
            ..Default::default()
        };
        let mut dens = DensifyStats {
            cameras_per_step,
            ..Default::default()
        };
        dens.reset(n);
        let stats = detach(py, || {
            self.locked()?.backward(
                &scene,
                colors,
                &grads,
                &mut out,
                view.then_some(&mut vg),
                Some(&mut dens),
            )
        })?;
        let d = PyDict::new(py);
        let bad = |e: numpy::ndarray::ShapeError| PyValueError::new_err(e.to_string());
        let put2 = |name: &str, v: Vec<f32>, cols: usize| -> PyResult<()> {
            let rows = v.len().checked_div(cols).unwrap_or(0);
            d.set_item(
                name,
                Array2::from_shape_vec((rows, cols), v)
                    .map_err(bad)?
                    .into_pyarray(py),
            )
        };
        let put1 = |name: &str, v: Vec<f32>| -> PyResult<()> {
            let a: Bound<'_, PyArray1<f32>> = Array1::from_vec(v).into_pyarray(py);
            d.set_item(name, a)
        };
        put2("means", out.means, 3)?;
        put2("quats", out.quats, 4)?;
        put2("log_scales", out.log_scales, 3)?;
        put1("opacity_logits", out.opacity_logits)?;
        put2("sh0", out.sh0, 3)?;
        d.set_item(
            "sh_rest",
            Array3::from_shape_vec((n, k, 3), out.sh_rest)
                .map_err(bad)?
                .into_pyarray(py),
        )?;
        put2("scales", out.scales, 3)?;
        put1("opacities", out.opacities)?;
        if colors.is_some() {
            put2("colors", out.colors, 3)?;
        }
        put1("background", out.background.to_vec())?;
        put1("grad2d", dens.grad2d)?;
        put1("grad2d_abs", dens.grad2d_abs)?;
        put1("count", dens.count)?;
        put1("max_radius", dens.max_radius)?;
        if view {
            put2("means2d", vg.means2d, 2)?;
            put2("means2d_abs", vg.means2d_abs, 2)?;
            put2("conics", vg.conics, 3)?;
            put2("view_colors", vg.colors, 3)?;
            put1("view_opacities", vg.opacities)?;
            put1("view_depths", vg.depths)?;
        }
        if let Some(m) = vg.viewmat {
            let a = Array2::from_shape_vec((4, 4), m.to_vec()).map_err(bad)?;
            d.set_item("viewmat", a.into_pyarray(py))?;
        }
        let s = PyDict::new(py);
        s.set_item("evaluations", stats.evaluations)?;
        s.set_item("intersections", stats.intersections)?;
        s.set_item("bands", stats.bands)?;
        s.set_item("slot_bytes", stats.slot_bytes)?;
        s.set_item("blend_s", stats.blend_s)?;
        s.set_item("reduce_s", stats.reduce_s)?;
        s.set_item("project_s", stats.project_s)?;
        d.set_item("stats", s)?;
        Ok(d)
    }

    /// The last forward's projection of every Gaussian (gsplat's `fully_fused_projection`
    /// outputs): radii (N,2) int32 (0 where culled), means2d (N,2), depths (N,), conics (N,3),
    /// opacities (N,) after compensation, colors (N,3).
    ///
    /// Raises:
    ///     ValueError: no forward yet.
    fn projection<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let p = self
            .lock()?
            .projection()
            .ok_or_else(|| PyValueError::new_err("projection needs a forward first"))?;
        crate::render::projection_dict(py, p)
    }

    /// Every contributing (pixel, Gaussian) pair of the last forward in blend order per pixel:
    /// (pixel index y*W+x (int64), Gaussian index (int64), alpha clamped at max_alpha (bool)).
    /// For reference checks on small images.
    fn contributions<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(
        Bound<'py, PyArray1<i64>>,
        Bound<'py, PyArray1<i64>>,
        Bound<'py, PyArray1<bool>>,
    )> {
        let ws = self.lock()?;
        let c = ws.contributions().map_err(CoreError)?;
        let pix: Vec<i64> = c.iter().map(|x| x.0 as i64).collect();
        let ids: Vec<i64> = c.iter().map(|x| x.1 as i64).collect();
        let cl: Vec<bool> = c.iter().map(|x| x.2).collect();
        Ok((
            Array1::from_vec(pix).into_pyarray(py),
            Array1::from_vec(ids).into_pyarray(py),
            Array1::from_vec(cl).into_pyarray(py),
        ))
    }
}

impl PyDiffRasterizer {
    /// The workspace, waited for without the GIL (called inside `detach`).
    fn locked(&self) -> splat_core::Result<std::sync::MutexGuard<'_, Workspace>> {
        self.ws.lock().map_err(|_| {
            splat_core::Error::InvalidArgument("DiffRasterizer is unusable after a panic".into())
        })
    }

    /// The workspace while holding the GIL: never waits (another thread may be rendering with
    /// it, and waiting here would keep that thread from taking the GIL back).
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, Workspace>> {
        self.ws
            .try_lock()
            .map_err(|_| PyRuntimeError::new_err("this DiffRasterizer is in use by another thread"))
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyDiffRasterizer>()?;
    Ok(())
}
