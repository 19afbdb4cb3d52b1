//! `GaussianScene`: SPEC §1 fields as read-only float32 NumPy arrays owned by the scene.
use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayDescrMethods, PyArrayMethods,
    PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyIndexError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use splat_core::scene::{sh_rest_count, SH_C0};
use splat_core::{Scene, SceneView};

use crate::errors::CoreError;

/// A 3D Gaussian Splatting scene of N Gaussians, stored pre-activation as float32 arrays.
///
/// Fields (read-only NumPy views, no copy): means (N,3), quats (N,4) unit (w,x,y,z),
/// log_scales (N,3), opacity_logits (N,), sh0 (N,3), sh_rest (N,K,3) with K = (d+1)^2-1.
/// Activated: scales = exp(log_scales), opacities = sigmoid(opacity_logits),
/// colors = 0.5 + C0*sh0.
#[pyclass(name = "GaussianScene", module = "morphgs._core", frozen)]
pub struct PyGaussianScene {
    means: Py<PyArray2<f32>>,
    quats: Py<PyArray2<f32>>,
    log_scales: Py<PyArray2<f32>>,
    opacity_logits: Py<PyArray1<f32>>,
    sh0: Py<PyArray2<f32>>,
    sh_rest: Py<PyArray3<f32>>,
    sh_degree: u8,
    extras: Vec<(String, Py<PyArray1<f32>>)>,
}

/// Read-only borrows of a scene's arrays, alive while core code reads them.
pub struct SceneBorrow<'py> {
    means: PyReadonlyArray2<'py, f32>,
    quats: PyReadonlyArray2<'py, f32>,
    log_scales: PyReadonlyArray2<'py, f32>,
    opacity_logits: PyReadonlyArray1<'py, f32>,
    sh0: PyReadonlyArray2<'py, f32>,
    sh_rest: PyReadonlyArray3<'py, f32>,
    sh_degree: u8,
}

fn contiguous<T>(r: Result<T, numpy::AsSliceError>) -> PyResult<T> {
    r.map_err(|e| PyValueError::new_err(e.to_string()))
}

impl SceneBorrow<'_> {
    /// The core view over the NumPy buffers (no copy).
    pub fn view(&self) -> PyResult<SceneView<'_>> {
        SceneView::new(
            contiguous(self.means.as_slice())?,
            contiguous(self.quats.as_slice())?,
            contiguous(self.log_scales.as_slice())?,
            contiguous(self.opacity_logits.as_slice())?,
            contiguous(self.sh0.as_slice())?,
            contiguous(self.sh_rest.as_slice())?,
            self.sh_degree,
        )
        .map_err(|e| CoreError(e).into())
    }
}

fn readonly<'py, A>(a: Bound<'py, A>) -> PyResult<Bound<'py, A>> {
    let kwargs = PyDict::new(a.py());
    kwargs.set_item("write", false)?;
    a.as_any().call_method("setflags", (), Some(&kwargs))?;
    Ok(a)
}

fn shape_err(name: &str, want: &str, got: &[usize]) -> PyErr {
    PyValueError::new_err(format!("{name} must have shape {want}, got {got:?}"))
}

/// Convert any real-valued array-like to a C-contiguous float32 array (no copy when it already is).
fn to_f32_array<'py>(
    py: Python<'py>,
    name: &str,
    obj: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyUntypedArray>> {
    let np = py.import("numpy")?;
    let arr = np.call_method1("asarray", (obj,))?;
    let arr = arr
        .cast_into::<PyUntypedArray>()
        .map_err(|_| PyTypeError::new_err(format!("{name} must be an array of numbers")))?;
    let kind = arr.dtype().kind();
    if !matches!(kind, b'f' | b'i' | b'u' | b'b') {
        return Err(PyTypeError::new_err(format!(
            "{name} must hold real numbers, got dtype {}",
            arr.dtype()
        )));
    }
    // A C-contiguous float32 view or copy; `vec_of` then copies it once into the scene's buffer.
    let kwargs = PyDict::new(py);
    kwargs.set_item("dtype", np.getattr("float32")?)?;
    let out = np.call_method("ascontiguousarray", (arr,), Some(&kwargs))?;
    Ok(out.cast_into::<PyUntypedArray>()?)
}

impl PyGaussianScene {
    /// Wrap an owned core scene; its vectors become the NumPy buffers (no copy).
    pub fn from_core(py: Python<'_>, scene: Scene) -> PyResult<Self> {
        scene.validate().map_err(CoreError)?;
        let n = scene.len();
        let k = sh_rest_count(scene.sh_degree);
        let bad = |e: numpy::ndarray::ShapeError| PyValueError::new_err(e.to_string());
        Ok(PyGaussianScene {
            means: readonly(
                Array2::from_shape_vec((n, 3), scene.means)
                    .map_err(bad)?
                    .into_pyarray(py),
            )?
            .unbind(),
            quats: readonly(
                Array2::from_shape_vec((n, 4), scene.quats)
                    .map_err(bad)?
                    .into_pyarray(py),
            )?
            .unbind(),
            log_scales: readonly(
                Array2::from_shape_vec((n, 3), scene.log_scales)
                    .map_err(bad)?
                    .into_pyarray(py),
            )?
            .unbind(),
            opacity_logits: readonly(Array1::from_vec(scene.opacity_logits).into_pyarray(py))?
                .unbind(),
            sh0: readonly(
                Array2::from_shape_vec((n, 3), scene.sh0)
                    .map_err(bad)?
                    .into_pyarray(py),
            )?
            .unbind(),
            sh_rest: readonly(
                Array3::from_shape_vec((n, k, 3), scene.sh_rest)
                    .map_err(bad)?
                    .into_pyarray(py),
            )?
            .unbind(),
            sh_degree: scene.sh_degree,
            extras: scene
                .extras
                .into_iter()
                .map(|(name, v)| {
                    Ok((
                        name,
                        readonly(Array1::from_vec(v).into_pyarray(py))?.unbind(),
                    ))
                })
                .collect::<PyResult<_>>()?,
        })
    }

    /// Borrow the arrays for reading by core code.
    pub fn borrow<'py>(&self, py: Python<'py>) -> PyResult<SceneBorrow<'py>> {
        Ok(SceneBorrow {
            means: self.means.bind(py).try_readonly()?,
            quats: self.quats.bind(py).try_readonly()?,
            log_scales: self.log_scales.bind(py).try_readonly()?,
            opacity_logits: self.opacity_logits.bind(py).try_readonly()?,
            sh0: self.sh0.bind(py).try_readonly()?,
            sh_rest: self.sh_rest.bind(py).try_readonly()?,
            sh_degree: self.sh_degree,
        })
    }

    pub fn extras_readonly<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<Vec<(String, PyReadonlyArray1<'py, f32>)>> {
        self.extras
            .iter()
            .map(|(n, a)| Ok((n.clone(), a.bind(py).try_readonly()?)))
            .collect()
    }

    /// A copy of the scene as an owned core scene (with extras).
    pub fn to_core(&self, py: Python<'_>) -> PyResult<Scene> {
        let b = self.borrow(py)?;
        let mut s = b.view()?.to_owned_scene();
        for (n, a) in self.extras_readonly(py)? {
            s.extras.push((n, contiguous(a.as_slice())?.to_vec()));
        }
        Ok(s)
    }

    pub fn sh_degree(&self) -> u8 {
        self.sh_degree
    }

    /// A scene holding the given arrays and sharing this scene's other arrays (no copy: every
    /// array of a scene is read-only). Each given array must have this scene's length.
    pub fn with_arrays(
        &self,
        py: Python<'_>,
        means: Option<Vec<f32>>,
        quats: Option<Vec<f32>>,
        log_scales: Option<Vec<f32>>,
        opacity_logits: Option<Vec<f32>>,
        sh0: Option<Vec<f32>>,
    ) -> PyResult<Self> {
        let n = self.len_py(py);
        let rows = |v: Vec<f32>, w: usize| -> PyResult<Py<PyArray2<f32>>> {
            let a = Array2::from_shape_vec((n, w), v)
                .map_err(|e| PyValueError::new_err(e.to_string()))?;
            Ok(readonly(a.into_pyarray(py))?.unbind())
        };
        let pick = |new: Option<Vec<f32>>, old: &Py<PyArray2<f32>>, w: usize| match new {
            Some(v) => rows(v, w),
            None => Ok(old.clone_ref(py)),
        };
        let opacity_logits = match opacity_logits {
            Some(v) if v.len() == n => readonly(Array1::from_vec(v).into_pyarray(py))?.unbind(),
            Some(v) => {
                return Err(PyValueError::new_err(format!(
                    "opacity_logits holds {} values, expected {n}",
                    v.len()
                )))
            }
            None => self.opacity_logits.clone_ref(py),
        };
        Ok(PyGaussianScene {
            means: pick(means, &self.means, 3)?,
            quats: pick(quats, &self.quats, 4)?,
            log_scales: pick(log_scales, &self.log_scales, 3)?,
            opacity_logits,
            sh0: pick(sh0, &self.sh0, 3)?,
            sh_rest: self.sh_rest.clone_ref(py),
            sh_degree: self.sh_degree,
            extras: self
                .extras
                .iter()
                .map(|(name, a)| (name.clone(), a.clone_ref(py)))
                .collect(),
        })
    }

    fn len_py(&self, py: Python<'_>) -> usize {
        self.opacity_logits.bind(py).len()
    }

    /// A scene sharing this scene's arrays with the extras `extra` set (replacing those of the
    /// same names, appended after the others). Each must have this scene's length.
    pub fn with_extras(&self, py: Python<'_>, extra: Vec<(String, Vec<f32>)>) -> PyResult<Self> {
        let n = self.len_py(py);
        if let Some((name, v)) = extra.iter().find(|(_, v)| v.len() != n) {
            return Err(PyValueError::new_err(format!(
                "extras['{name}'] holds {} values, expected {n}",
                v.len()
            )));
        }
        let mut out = self.with_arrays(py, None, None, None, None, None)?;
        out.extras
            .retain(|(name, _)| !extra.iter().any(|(e, _)| e == name));
        for (name, v) in extra {
            out.extras.push((
                name,
                readonly(Array1::from_vec(v).into_pyarray(py))?.unbind(),
            ));
        }
        Ok(out)
    }
}

#[pymethods]
impl PyGaussianScene {
    /// Build a scene from arrays (any real dtype; copied to float32). Quaternions are normalised.
    ///
    /// Args:
    ///     means: (N,3). quats: (N,4) (w,x,y,z). log_scales: (N,3). opacity_logits: (N,).
    ///     sh0: (N,3). sh_rest: None or (N,K,3) with K in {0,3,8,15,24} (degree 0..4).
    ///     extras: optional mapping name -> (N,) array, kept and written back by save_ply.
    ///
    /// Raises:
    ///     ValueError: a shape is wrong or the sizes disagree.
    ///     TypeError: an array does not hold real numbers.
    #[staticmethod]
    #[pyo3(signature = (*, means, quats, log_scales, opacity_logits, sh0, sh_rest = None, extras = None))]
    fn from_arrays(
        py: Python<'_>,
        means: &Bound<'_, PyAny>,
        quats: &Bound<'_, PyAny>,
        log_scales: &Bound<'_, PyAny>,
        opacity_logits: &Bound<'_, PyAny>,
        sh0: &Bound<'_, PyAny>,
        sh_rest: Option<&Bound<'_, PyAny>>,
        extras: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let means = to_f32_array(py, "means", means)?;
        let n = means.shape().first().copied().unwrap_or(0);
        let check = |name: &str,
                     a: &Bound<'_, PyUntypedArray>,
                     want: &[usize],
                     desc: &str|
         -> PyResult<()> {
            if a.shape() != want {
                return Err(shape_err(name, desc, a.shape()));
            }
            Ok(())
        };
        check("means", &means, &[n, 3], "(N,3)")?;
        let quats = to_f32_array(py, "quats", quats)?;
        check("quats", &quats, &[n, 4], &format!("({n},4)"))?;
        let log_scales = to_f32_array(py, "log_scales", log_scales)?;
        check("log_scales", &log_scales, &[n, 3], &format!("({n},3)"))?;
        let opac = to_f32_array(py, "opacity_logits", opacity_logits)?;
        check("opacity_logits", &opac, &[n], &format!("({n},)"))?;
        let sh0 = to_f32_array(py, "sh0", sh0)?;
        check("sh0", &sh0, &[n, 3], &format!("({n},3)"))?;
        let (rest, degree) = match sh_rest {
            None => (Vec::new(), 0u8),
            Some(r) if r.is_none() => (Vec::new(), 0u8),
            Some(r) => {
                let r = to_f32_array(py, "sh_rest", r)?;
                let shape = r.shape().to_vec();
                if shape.len() != 3 || shape[0] != n || shape[2] != 3 {
                    return Err(shape_err("sh_rest", &format!("({n},K,3)"), &shape));
                }
                let Some(d) = splat_core::scene::sh_degree_for_rest(shape[1]) else {
                    return Err(PyValueError::new_err(format!(
                        "sh_rest has K={} coefficients per channel, which is no SH degree \
                         (K must be 0, 3, 8, 15 or 24 for degree 0..4)",
                        shape[1]
                    )));
                };
                (vec_of(&r)?, d)
            }
        };
        let mut scene = Scene {
            means: vec_of(&means)?,
            quats: vec_of(&quats)?,
            log_scales: vec_of(&log_scales)?,
            opacity_logits: vec_of(&opac)?,
            sh0: vec_of(&sh0)?,
            sh_rest: rest,
            sh_degree: degree,
            extras: Vec::new(),
        };
        if let Some(extras) = extras {
            let names: Vec<String> = extras
                .keys()
                .iter()
                .map(|k| k.extract::<String>())
                .collect::<PyResult<_>>()?;
            splat_core::ply::check_extra_names(names.iter().map(String::as_str))
                .map_err(CoreError)?;
            for (k, v) in extras.iter() {
                let name: String = k.extract()?;
                let a = to_f32_array(py, &format!("extras['{name}']"), &v)?;
                check(&format!("extras['{name}']"), &a, &[n], &format!("({n},)"))?;
                scene.extras.push((name, vec_of(&a)?));
            }
        }
        scene.normalize_quats();
        Self::from_core(py, scene)
    }

    /// (N,3) Gaussian centres.
    #[getter]
    fn means(&self, py: Python<'_>) -> Py<PyArray2<f32>> {
        self.means.clone_ref(py)
    }
    /// (N,4) unit quaternions (w,x,y,z).
    #[getter]
    fn quats(&self, py: Python<'_>) -> Py<PyArray2<f32>> {
        self.quats.clone_ref(py)
    }
    /// (N,3) natural-log axis scales.
    #[getter]
    fn log_scales(&self, py: Python<'_>) -> Py<PyArray2<f32>> {
        self.log_scales.clone_ref(py)
    }
    /// (N,) opacity logits.
    #[getter]
    fn opacity_logits(&self, py: Python<'_>) -> Py<PyArray1<f32>> {
        self.opacity_logits.clone_ref(py)
    }
    /// (N,3) DC spherical-harmonic coefficients.
    #[getter]
    fn sh0(&self, py: Python<'_>) -> Py<PyArray2<f32>> {
        self.sh0.clone_ref(py)
    }
    /// (N,K,3) higher SH bands, basis-major, channel-last.
    #[getter]
    fn sh_rest(&self, py: Python<'_>) -> Py<PyArray3<f32>> {
        self.sh_rest.clone_ref(py)
    }
    /// SH degree 0..4.
    #[getter(sh_degree)]
    fn get_sh_degree(&self) -> u8 {
        self.sh_degree
    }
    /// Extra per-Gaussian properties the file carried, name -> (N,) float32 array.
    #[getter]
    fn extras<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (n, a) in &self.extras {
            d.set_item(n, a.bind(py))?;
        }
        Ok(d)
    }
    /// (N,3) linear scales exp(log_scales) (a new array).
    #[getter]
    fn scales<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let a = self.log_scales.bind(py).try_readonly()?;
        Ok(a.as_array().mapv(f32::exp).into_pyarray(py))
    }
    /// (N,) opacities sigmoid(opacity_logits) (a new array).
    #[getter]
    fn opacities<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let a = self.opacity_logits.bind(py).try_readonly()?;
        Ok(a.as_array()
            .mapv(|x| 1.0 / (1.0 + (-x).exp()))
            .into_pyarray(py))
    }
    /// (N,3) DC colours 0.5 + C0*sh0 (a new array, not clamped).
    #[getter]
    fn colors<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let a = self.sh0.bind(py).try_readonly()?;
        Ok(a.as_array().mapv(|x| 0.5 + SH_C0 * x).into_pyarray(py))
    }

    /// Axis-aligned bounds of the finite centres as (min, max), each a (3,) float32 array.
    /// An empty scene gives NaNs.
    fn bounds<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let b = self.borrow(py)?;
        let (lo, hi) = b.view()?.bounds().unwrap_or(([f32::NAN; 3], [f32::NAN; 3]));
        PyTuple::new(
            py,
            [lo.to_vec().into_pyarray(py), hi.to_vec().into_pyarray(py)],
        )
    }

    /// A new scene holding the selected Gaussians (extras follow).
    ///
    /// Args:
    ///     indices_or_mask: a boolean mask of length N, or integer indices (negative count from
    ///         the end; repeats allowed).
    fn subset(&self, py: Python<'_>, indices_or_mask: &Bound<'_, PyAny>) -> PyResult<Self> {
        let n = self.len_py(py);
        let np = py.import("numpy")?;
        let arr = np
            .call_method1("asarray", (indices_or_mask,))?
            .cast_into::<PyUntypedArray>()?;
        let kind = arr.dtype().kind();
        let idx: Vec<usize> = if kind == b'b' {
            if arr.shape() != [n] {
                return Err(PyValueError::new_err(format!(
                    "a boolean mask must have shape ({n},), got {:?}",
                    arr.shape()
                )));
            }
            let m: Vec<bool> = arr.call_method0("tolist")?.extract()?;
            m.iter()
                .enumerate()
                .filter_map(|(i, &k)| k.then_some(i))
                .collect()
        } else if matches!(kind, b'i' | b'u') || arr.len() == 0 {
            if arr.ndim() != 1 {
                return Err(PyValueError::new_err("indices must be one-dimensional"));
            }
            let raw: Vec<i64> = np
                .call_method1("asarray", (arr, np.getattr("int64")?))?
                .call_method0("tolist")?
                .extract()?;
            raw.iter()
                .map(|&i| {
                    let j = if i < 0 { i + n as i64 } else { i };
                    if j < 0 || j >= n as i64 {
                        Err(PyIndexError::new_err(format!(
                            "index {i} is out of range for a scene of {n} Gaussians"
                        )))
                    } else {
                        Ok(j as usize)
                    }
                })
                .collect::<PyResult<_>>()?
        } else {
            return Err(PyTypeError::new_err(format!(
                "subset takes a boolean mask or integer indices, got dtype {}",
                arr.dtype()
            )));
        };
        let core = self.to_core(py)?;
        Self::from_core(py, py.detach(|| crate::pool::install(|| core.gather(&idx))))
    }

    fn __len__(&self, py: Python<'_>) -> usize {
        self.len_py(py)
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let extras: Vec<&str> = self.extras.iter().map(|(n, _)| n.as_str()).collect();
        format!(
            "GaussianScene(n={}, sh_degree={}{})",
            self.len_py(py),
            self.sh_degree,
            if extras.is_empty() {
                String::new()
            } else {
                format!(", extras={extras:?}")
            }
        )
    }

    /// Pickle support (e.g. for worker processes): rebuilds through from_arrays.
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, (Bound<'py, PyDict>,))> {
        let py = slf.py();
        let s = slf.get();
        let state = PyDict::new(py);
        state.set_item("means", s.means.bind(py))?;
        state.set_item("quats", s.quats.bind(py))?;
        state.set_item("log_scales", s.log_scales.bind(py))?;
        state.set_item("opacity_logits", s.opacity_logits.bind(py))?;
        state.set_item("sh0", s.sh0.bind(py))?;
        state.set_item("sh_rest", s.sh_rest.bind(py))?;
        state.set_item("extras", s.extras(py)?)?;
        let ctor = py.import("morphgs._core")?.getattr("_scene_from_state")?;
        Ok((ctor, (state,)))
    }
}

/// Copy a contiguous float32 array into a new buffer the scene owns (huge pages when large).
fn vec_of(a: &Bound<'_, PyUntypedArray>) -> PyResult<Vec<f32>> {
    let a = a.cast::<numpy::PyArrayDyn<f32>>()?;
    let ro = a.try_readonly()?;
    let src = contiguous(ro.as_slice())?;
    let mut v = splat_core::mem::zeroed_f32(src.len());
    v.copy_from_slice(src);
    Ok(v)
}

/// Rebuild a pickled scene (internal).
#[pyfunction]
fn _scene_from_state(py: Python<'_>, state: &Bound<'_, PyDict>) -> PyResult<PyGaussianScene> {
    let get = |k: &str| -> PyResult<Bound<'_, PyAny>> {
        state
            .get_item(k)?
            .ok_or_else(|| PyValueError::new_err(format!("scene state lacks '{k}'")))
    };
    let extras = get("extras")?.cast_into::<PyDict>()?;
    PyGaussianScene::from_arrays(
        py,
        &get("means")?,
        &get("quats")?,
        &get("log_scales")?,
        &get("opacity_logits")?,
        &get("sh0")?,
        Some(&get("sh_rest")?),
        Some(&extras),
    )
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyGaussianScene>()?;
    m.add_function(wrap_pyfunction!(_scene_from_state, m)?)?;
    Ok(())
}
