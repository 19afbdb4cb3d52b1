//! `_core.Trainer` (the optimiser loop of `splat_core::fit`, run once per call with the GIL
//! released and a Python callback for progress, evaluation and checkpoints) and the init
//! helpers `_fit_init_scene`, `_fit_random_points` and `_fit_loss`. The Python API is
//! `morphgs/fit/`.
use std::path::PathBuf;
use std::sync::Mutex;
use std::time::Instant;

use numpy::ndarray::{Array2, Array3};
use numpy::{
    IntoPyArray, PyArray2, PyArray3, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use splat_core::camera::Camera;
use splat_core::fit::{
    self, checkpoint, init, DefaultStrategy, Event, FitConfig, Flow, Hooks, McmcStrategy, RunEnd,
    RunOptions, StepRecord, Strategy, Trainer, View,
};
use splat_core::raster::RenderOptions;

use crate::errors::{detach, CoreError};
use crate::scene::PyGaussianScene;

/// A value of `d[key]` converted to T, `default` when absent; the error names the key.
fn get<'py, T: pyo3::conversion::FromPyObjectOwned<'py>>(
    d: &Bound<'py, PyDict>,
    key: &str,
    default: T,
) -> PyResult<T> {
    match d.get_item(key)? {
        None => Ok(default),
        Some(v) => v.extract::<T>().map_err(|e| {
            let e: PyErr = e.into();
            PyValueError::new_err(format!("config field '{key}': {e}"))
        }),
    }
}

fn section<'py>(d: &Bound<'py, PyDict>, key: &str) -> PyResult<Bound<'py, PyDict>> {
    match d.get_item(key)? {
        None => Ok(PyDict::new(d.py())),
        Some(v) => v
            .cast_into::<PyDict>()
            .map_err(|_| PyValueError::new_err(format!("config section '{key}' must be a table"))),
    }
}

/// The core config from the dict `morphgs.fit.FitConfig.native()` builds.
fn config_from(d: &Bound<'_, PyDict>) -> PyResult<FitConfig> {
    let base = FitConfig::default();
    let lr_d = section(d, "lr")?;
    let l = base.lr;
    let lr = fit::LearningRates {
        means: get(&lr_d, "means", l.means)?,
        means_final: get(&lr_d, "means_final", l.means_final)?,
        quats: get(&lr_d, "quats", l.quats)?,
        scales: get(&lr_d, "scales", l.scales)?,
        opacities: get(&lr_d, "opacities", l.opacities)?,
        sh0: get(&lr_d, "sh0", l.sh0)?,
        sh_rest: get(&lr_d, "sh_rest", l.sh_rest)?,
    };
    let strategy = match get::<String>(d, "strategy", "default".into())?.as_str() {
        "default" => {
            let s = section(d, "default")?;
            let b = DefaultStrategy::default();
            Strategy::Default(DefaultStrategy {
                grow_grad2d: get(&s, "grow_grad2d", b.grow_grad2d)?,
                grow_scale3d: get(&s, "grow_scale3d", b.grow_scale3d)?,
                prune_opa: get(&s, "prune_opa", b.prune_opa)?,
                prune_scale3d: get(&s, "prune_scale3d", b.prune_scale3d)?,
                refine_start: get(&s, "refine_start", b.refine_start)?,
                refine_stop: get(&s, "refine_stop", b.refine_stop)?,
                refine_every: get(&s, "refine_every", b.refine_every)?,
                reset_every: get(&s, "reset_every", b.reset_every)?,
                opacity_reset: get(&s, "opacity_reset", b.opacity_reset)?,
                absgrad: get(&s, "absgrad", b.absgrad)?,
                revised_opacity: get(&s, "revised_opacity", b.revised_opacity)?,
            })
        }
        "mcmc" => {
            let s = section(d, "mcmc")?;
            let b = McmcStrategy::default();
            Strategy::Mcmc(McmcStrategy {
                cap_max: get(&s, "cap_max", b.cap_max)?,
                noise_lr: get(&s, "noise_lr", b.noise_lr)?,
                refine_start: get(&s, "refine_start", b.refine_start)?,
                refine_stop: get(&s, "refine_stop", b.refine_stop)?,
                refine_every: get(&s, "refine_every", b.refine_every)?,
                min_opacity: get(&s, "min_opacity", b.min_opacity)?,
                opacity_reg: get(&s, "opacity_reg", b.opacity_reg)?,
                scale_reg: get(&s, "scale_reg", b.scale_reg)?,
            })
        }
        other => {
            return Err(PyValueError::new_err(format!(
                "config field 'strategy' must be \"default\" or \"mcmc\", got {other:?}"
            )))
        }
    };
    let adam_d = section(d, "adam")?;
    let a = base.adam;
    let cfg = FitConfig {
        steps: get(d, "steps", base.steps)?,
        seed: get(d, "seed", base.seed)?,
        scene_scale: get(d, "scene_scale", base.scene_scale)?,
        sh_degree: get(d, "sh_degree", base.sh_degree)?,
        sh_degree_interval: get(d, "sh_degree_interval", base.sh_degree_interval)?,
        ssim_lambda: get(d, "ssim_lambda", base.ssim_lambda)?,
        lr,
        adam: fit::params::AdamParams {
            beta1: get(&adam_d, "beta1", a.beta1)?,
            beta2: get(&adam_d, "beta2", a.beta2)?,
            eps: get(&adam_d, "eps", a.eps)?,
        },
        strategy,
        render: RenderOptions {
            background: get(d, "background", base.render.background)?,
            max_alpha: get(d, "max_alpha", base.render.max_alpha)?,
            antialiased: get(d, "antialiased", base.render.antialiased)?,
            sh_degree: None,
            simd: crate::render::simd_from_env()?,
            count_useful: false,
        },
    };
    cfg.validate().map_err(CoreError)?;
    Ok(cfg)
}

/// Posed images: (H,W,3) uint8 arrays with (V,4,4) world-to-camera and (V,3,3) intrinsics,
/// and optional masks: a list of None or (H,W) uint8 arrays (0: the pixel is ignored).
fn views_from(
    images: &Bound<'_, PyList>,
    w2c: Option<PyReadonlyArray3<'_, f64>>,
    k: Option<PyReadonlyArray3<'_, f64>>,
    masks: Option<&Bound<'_, PyList>>,
    what: &str,
) -> PyResult<Vec<View>> {
    let n = images.len();
    if n == 0 {
        return Ok(Vec::new());
    }
    let (Some(w2c), Some(k)) = (w2c, k) else {
        return Err(PyValueError::new_err(format!(
            "{what}: cameras (world_to_camera and K) are needed with the images"
        )));
    };
    let (ws, ks) = (w2c.shape().to_vec(), k.shape().to_vec());
    if ws != [n, 4, 4] || ks != [n, 3, 3] {
        return Err(PyValueError::new_err(format!(
            "{what}: {n} images need world_to_camera ({n},4,4) and K ({n},3,3), got {ws:?} and {ks:?}"
        )));
    }
    let w = w2c
        .as_slice()
        .map_err(|_| PyValueError::new_err("world_to_camera must be C-contiguous"))?;
    let kk = k
        .as_slice()
        .map_err(|_| PyValueError::new_err("K must be C-contiguous"))?;
    let mut out = Vec::with_capacity(n);
    for (i, item) in images.iter().enumerate() {
        let img: PyReadonlyArray3<'_, u8> = item.extract().map_err(|_| {
            PyTypeError::new_err(format!("{what} image {i} must be a (H,W,3) uint8 array"))
        })?;
        let sh = img.shape();
        if sh[2] != 3 {
            return Err(PyValueError::new_err(format!(
                "{what} image {i} must be (H,W,3), got {sh:?}"
            )));
        }
        let cam = Camera::from_matrices(
            &w[i * 16..i * 16 + 16],
            &kk[i * 9..i * 9 + 9],
            sh[1] as u32,
            sh[0] as u32,
            0.01,
            1e10,
        )
        .map_err(CoreError)?;
        let pixels = img
            .as_slice()
            .map_err(|_| PyValueError::new_err(format!("{what} image {i} must be C-contiguous")))?
            .to_vec();
        let mut view = View::new(cam, pixels).map_err(CoreError)?;
        if let Some(ms) = masks {
            let item = ms.get_item(i)?;
            if !item.is_none() {
                let m: PyReadonlyArray2<'_, u8> = item.extract().map_err(|_| {
                    PyTypeError::new_err(format!("{what} mask {i} must be a (H,W) uint8 array"))
                })?;
                if m.shape() != [sh[0], sh[1]] {
                    return Err(PyValueError::new_err(format!(
                        "{what} mask {i} is {:?}, its image is {}x{}",
                        m.shape(),
                        sh[1],
                        sh[0]
                    )));
                }
                let mv = m
                    .as_slice()
                    .map_err(|_| {
                        PyValueError::new_err(format!("{what} mask {i} must be C-contiguous"))
                    })?
                    .to_vec();
                view = view
                    .with_mask(mv)
                    .map_err(|e| PyValueError::new_err(format!("{what} mask {i}: {e}")))?;
            }
        }
        out.push(view);
    }
    if let Some(ms) = masks {
        if ms.len() != n {
            return Err(PyValueError::new_err(format!(
                "{what}: {} masks for {n} images",
                ms.len()
            )));
        }
    }
    Ok(out)
}

/// The optimiser of `morphgs fit` over posed images (see `morphgs.fit`). Not for concurrent
/// use: a second call while `run` works raises RuntimeError.
#[pyclass(name = "Trainer", module = "morphgs._core", frozen)]
pub struct PyTrainer {
    inner: Mutex<Trainer>,
}

/// Buffers step records and hands them to the Python callback, checks Ctrl-C each step.
struct PyHooks {
    callback: Option<Py<PyAny>>,
    pending: Vec<StepRecord>,
    last: Instant,
    every_s: f64,
    error: Option<PyErr>,
}

fn record_dict<'py>(py: Python<'py>, r: &StepRecord) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("step", r.step)?;
    d.set_item("view", r.view)?;
    d.set_item("loss", r.loss)?;
    d.set_item("l1", r.l1)?;
    d.set_item("ssim", r.ssim)?;
    d.set_item("psnr", r.psnr)?;
    d.set_item("gaussians", r.gaussians)?;
    d.set_item("sh_degree", r.sh_degree)?;
    d.set_item("lr_means", r.lr_means)?;
    let f = &r.refine;
    d.set_item("duplicated", f.duplicated)?;
    d.set_item("split", f.split)?;
    d.set_item("pruned", f.pruned)?;
    d.set_item("reset", f.reset)?;
    d.set_item("relocated", f.relocated)?;
    d.set_item("added", f.added)?;
    d.set_item("seconds", r.seconds)?;
    d.set_item("forward_s", r.forward_s)?;
    d.set_item("loss_s", r.loss_s)?;
    d.set_item("backward_s", r.backward_s)?;
    d.set_item("adam_s", r.adam_s)?;
    d.set_item("strategy_s", r.strategy_s)?;
    Ok(d)
}

impl PyHooks {
    /// Call the Python callback with (kind, payload): Ok(Stop) when it returned True.
    fn try_call(&self, py: Python<'_>, kind: &str, payload: Bound<'_, PyAny>) -> PyResult<Flow> {
        let Some(cb) = &self.callback else {
            return Ok(Flow::Continue);
        };
        let v = cb.bind(py).call1((kind, payload))?;
        Ok(if v.is_truthy().unwrap_or(false) {
            Flow::Stop
        } else {
            Flow::Continue
        })
    }

    /// Call the Python callback with (kind, payload); True (or an exception) stops the run.
    fn call(&mut self, py: Python<'_>, kind: &str, payload: Bound<'_, PyAny>) -> Flow {
        self.try_call(py, kind, payload).unwrap_or_else(|e| {
            self.error.get_or_insert(e);
            Flow::Stop
        })
    }

    /// Hand the step records gathered since the last call to the callback. A batch the callback
    /// raised on (a Ctrl-C that landed in it) is kept and handed over again with the next one,
    /// at the latest at the checkpoint the stop writes: the callback cannot say how much of it
    /// it wrote, so it skips the steps it already has (fit.run's logger does), and no row before
    /// the checkpoint is lost.
    fn flush(&mut self, py: Python<'_>) -> Flow {
        if self.pending.is_empty() {
            return Flow::Continue;
        }
        self.last = Instant::now();
        let list = self
            .pending
            .iter()
            .map(|r| record_dict(py, r))
            .collect::<PyResult<Vec<_>>>()
            .and_then(|r| PyList::new(py, r));
        match list.and_then(|l| self.try_call(py, "steps", l.into_any())) {
            Ok(f) => {
                self.pending.clear();
                f
            }
            Err(e) => {
                self.error.get_or_insert(e);
                Flow::Stop
            }
        }
    }
}

impl Hooks for PyHooks {
    fn parallel(&mut self, work: &mut (dyn FnMut() + Send)) {
        crate::pool::install(work)
    }

    fn event(&mut self, e: Event<'_>) -> Flow {
        Python::attach(|py| {
            let mut flow = Flow::Continue;
            if let Err(err) = py.check_signals() {
                self.error.get_or_insert(err);
                flow = Flow::Stop;
            }
            let f = match e {
                Event::Step(r) => {
                    self.pending.push(*r);
                    if self.last.elapsed().as_secs_f64() >= self.every_s {
                        self.flush(py)
                    } else {
                        Flow::Continue
                    }
                }
                Event::EvalView {
                    step,
                    view,
                    metrics,
                    rgb,
                    width,
                    height,
                } => {
                    let mut f = self.flush(py);
                    let d = PyDict::new(py);
                    let arr =
                        Array3::from_shape_vec((height as usize, width as usize, 3), rgb.to_vec())
                            .map(|a| a.into_pyarray(py));
                    let filled = (|| -> PyResult<()> {
                        d.set_item("step", step)?;
                        d.set_item("view", view)?;
                        d.set_item("psnr", metrics.psnr)?;
                        d.set_item("ssim", metrics.ssim)?;
                        d.set_item(
                            "rgb",
                            arr.map_err(|e| PyValueError::new_err(e.to_string()))?,
                        )?;
                        Ok(())
                    })();
                    match filled {
                        Ok(()) => {
                            if self.call(py, "eval_view", d.into_any()) == Flow::Stop {
                                f = Flow::Stop;
                            }
                        }
                        Err(err) => {
                            self.error.get_or_insert(err);
                            f = Flow::Stop;
                        }
                    }
                    f
                }
                Event::Eval { step, psnr, ssim } => {
                    let d = PyDict::new(py);
                    let ok = d
                        .set_item("step", step)
                        .and(d.set_item("psnr", psnr))
                        .and(d.set_item("ssim", ssim));
                    match ok {
                        Ok(()) => self.call(py, "eval", d.into_any()),
                        Err(err) => {
                            self.error.get_or_insert(err);
                            Flow::Stop
                        }
                    }
                }
                Event::BeforeCheckpoint { .. } => self.flush(py),
                Event::Checkpoint { step } => {
                    let d = PyDict::new(py);
                    match d.set_item("step", step) {
                        Ok(()) => self.call(py, "checkpoint", d.into_any()),
                        Err(err) => {
                            self.error.get_or_insert(err);
                            Flow::Stop
                        }
                    }
                }
            };
            if f == Flow::Stop {
                flow = Flow::Stop;
            }
            flow
        })
    }
}

#[pymethods]
impl PyTrainer {
    /// A trainer at step 0.
    ///
    /// Args:
    ///     scene: the initial GaussianScene (SH bands cut or zero-padded to the config's degree).
    ///     images: training images, a list of (H,W,3) uint8 arrays.
    ///     world_to_camera: (V,4,4) float64; K: (V,3,3) float64, one per image (its size is the
    ///         image's).
    ///     config: the dict of `morphgs.fit.FitConfig.native()`.
    ///     eval_images, eval_world_to_camera, eval_K: held-out views, the same way.
    ///     masks, eval_masks: None, or one entry per image: None or a (H,W) uint8 mask (0: the
    ///         pixel is left out of the loss and the held-out metrics).
    ///
    /// Raises:
    ///     ValueError: a bad config (names the field), no training view, an empty scene,
    ///     images and cameras that disagree.
    #[new]
    #[pyo3(signature = (scene, images, world_to_camera, K, *, config, eval_images = None,
                        eval_world_to_camera = None, eval_K = None, masks = None, eval_masks = None))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        scene: &Bound<'_, PyGaussianScene>,
        images: &Bound<'_, PyList>,
        world_to_camera: PyReadonlyArray3<'_, f64>,
        K: PyReadonlyArray3<'_, f64>,
        config: &Bound<'_, PyDict>,
        eval_images: Option<&Bound<'_, PyList>>,
        eval_world_to_camera: Option<PyReadonlyArray3<'_, f64>>,
        eval_K: Option<PyReadonlyArray3<'_, f64>>,
        masks: Option<&Bound<'_, PyList>>,
        eval_masks: Option<&Bound<'_, PyList>>,
    ) -> PyResult<Self> {
        let cfg = config_from(config)?;
        let train = views_from(images, Some(world_to_camera), Some(K), masks, "training")?;
        let eval = match eval_images {
            Some(l) => views_from(l, eval_world_to_camera, eval_K, eval_masks, "held-out")?,
            None => Vec::new(),
        };
        let b = scene.get().borrow(py)?;
        let view = b.view()?;
        let t = detach(py, || Trainer::new(cfg, train, eval, &view))?;
        Ok(PyTrainer {
            inner: Mutex::new(t),
        })
    }

    /// A trainer restored from a checkpoint written by `run` with the same config, data and
    /// `fingerprint`.
    ///
    /// Raises:
    ///     FileNotFoundError: no checkpoint. SceneFormatError: a damaged checkpoint or one of
    ///     another run (other fingerprint).
    #[staticmethod]
    #[pyo3(signature = (path, images, world_to_camera, K, *, config, fingerprint,
                        eval_images = None, eval_world_to_camera = None, eval_K = None,
                        masks = None, eval_masks = None))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn restore(
        py: Python<'_>,
        path: PathBuf,
        images: &Bound<'_, PyList>,
        world_to_camera: PyReadonlyArray3<'_, f64>,
        K: PyReadonlyArray3<'_, f64>,
        config: &Bound<'_, PyDict>,
        fingerprint: &[u8],
        eval_images: Option<&Bound<'_, PyList>>,
        eval_world_to_camera: Option<PyReadonlyArray3<'_, f64>>,
        eval_K: Option<PyReadonlyArray3<'_, f64>>,
        masks: Option<&Bound<'_, PyList>>,
        eval_masks: Option<&Bound<'_, PyList>>,
    ) -> PyResult<Self> {
        let cfg = config_from(config)?;
        let train = views_from(images, Some(world_to_camera), Some(K), masks, "training")?;
        let eval = match eval_images {
            Some(l) => views_from(l, eval_world_to_camera, eval_K, eval_masks, "held-out")?,
            None => Vec::new(),
        };
        let t = detach(py, || {
            let ck = checkpoint::load(&path, fingerprint)?;
            Trainer::restore(cfg, train, eval, ck)
        })?;
        Ok(PyTrainer {
            inner: Mutex::new(t),
        })
    }

    /// Steps completed.
    #[getter]
    fn step(&self) -> PyResult<u32> {
        Ok(self.lock()?.step())
    }

    fn __len__(&self) -> PyResult<usize> {
        Ok(self.lock()?.len())
    }

    /// The current Gaussians as a GaussianScene (a copy).
    fn scene(&self, py: Python<'_>) -> PyResult<PyGaussianScene> {
        let s = self.lock()?.scene();
        PyGaussianScene::from_core(py, s)
    }

    /// The training view index step `step` (0-based) uses.
    fn view_at(&self, step: u32) -> PyResult<usize> {
        Ok(self.lock()?.view_at(step))
    }

    /// Train until `until` steps are done (at most the config's steps), in one native loop with
    /// the GIL released.
    ///
    /// Args:
    ///     until: the step count to reach.
    ///     callback: called as callback(kind, payload) with kind "steps" (a list of step-record
    ///         dicts, batched every `progress_every` seconds and before every checkpoint and
    ///         evaluation), "eval_view" (step, view, psnr, ssim, rgb (H,W,3) float32),
    ///         "eval" (step, mean psnr, mean ssim) and "checkpoint" (step). A true return
    ///         value stops the run (after a checkpoint). When the callback raises on a "steps"
    ///         batch (a Ctrl-C landing in it), the batch comes again with the next one, before
    ///         the checkpoint: skip the steps you already have.
    ///     eval_every: evaluate the held-out views every this many steps and at the end (0:
    ///         never).
    ///     checkpoint: checkpoint file, written atomically every `checkpoint_every` steps, at
    ///         the end and when the run stops (Ctrl-C, callback).
    ///     fingerprint: the run's identity stored in the checkpoint.
    ///     progress_every: seconds between "steps" callbacks.
    ///
    /// Returns:
    ///     "finished" or "stopped".
    ///
    /// Raises:
    ///     KeyboardInterrupt: Ctrl-C (after the checkpoint is written); whatever the callback
    ///     raised (likewise).
    #[pyo3(signature = (until, *, callback = None, eval_every = 0, checkpoint = None,
                        checkpoint_every = 0, fingerprint = None, progress_every = 0.5))]
    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        py: Python<'_>,
        until: u32,
        callback: Option<Py<PyAny>>,
        eval_every: u32,
        checkpoint: Option<PathBuf>,
        checkpoint_every: u32,
        fingerprint: Option<Vec<u8>>,
        progress_every: f64,
    ) -> PyResult<&'static str> {
        let mut guard = self.lock()?;
        let opts = RunOptions {
            until,
            eval_every,
            checkpoint,
            checkpoint_every,
            fingerprint: fingerprint.unwrap_or_default(),
        };
        let mut hooks = PyHooks {
            callback,
            pending: Vec::new(),
            last: Instant::now(),
            every_s: progress_every,
            error: None,
        };
        let t: &mut Trainer = &mut guard;
        let res = py.detach(|| {
            let r = fit::run(t, &opts, &mut hooks);
            if r.is_ok() {
                Python::attach(|py| hooks.flush(py));
            }
            r
        });
        if let Some(e) = hooks.error.take() {
            return Err(e);
        }
        match res.map_err(CoreError)? {
            RunEnd::Finished => Ok("finished"),
            RunEnd::Stopped => Ok("stopped"),
        }
    }

    /// Write a checkpoint of the current state now (atomically).
    #[pyo3(signature = (path, *, fingerprint = None))]
    fn save_checkpoint(
        &self,
        py: Python<'_>,
        path: PathBuf,
        fingerprint: Option<Vec<u8>>,
    ) -> PyResult<()> {
        let ck = self.lock()?.checkpoint(&fingerprint.unwrap_or_default());
        detach(py, || checkpoint::save(&path, &ck))
    }

    /// Held-out metrics now: a list of (psnr, ssim) per held-out view (render clamped to [0, 1]).
    fn evaluate(&self, py: Python<'_>) -> PyResult<Vec<(f64, f64)>> {
        let mut g = self.lock()?;
        let t: &mut Trainer = &mut g;
        let e = detach(py, || t.evaluate(|_, _, _| {}))?;
        Ok(e.iter().map(|v| (v.psnr, v.ssim)).collect())
    }

    /// Render with the current parameters (the SH degree in use): (H,W,3) float32.
    #[allow(non_snake_case)]
    fn render<'py>(
        &self,
        py: Python<'py>,
        world_to_camera: PyReadonlyArray2<'py, f64>,
        K: PyReadonlyArray2<'py, f64>,
        width: u32,
        height: u32,
    ) -> PyResult<Bound<'py, PyArray3<f32>>> {
        let (w, k) = (
            world_to_camera.as_slice().map_err(|_| {
                PyValueError::new_err("world_to_camera must be a C-contiguous (4,4) array")
            })?,
            K.as_slice()
                .map_err(|_| PyValueError::new_err("K must be a C-contiguous (3,3) array"))?,
        );
        let cam = Camera::from_matrices(w, k, width, height, 0.01, 1e10).map_err(CoreError)?;
        let g = self.lock()?;
        let t: &Trainer = &g;
        let rgb = detach(py, || t.render(&cam))?;
        Array3::from_shape_vec((height as usize, width as usize, 3), rgb)
            .map(|a| a.into_pyarray(py))
            .map_err(|e| PyValueError::new_err(e.to_string()))
    }
}

impl PyTrainer {
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, Trainer>> {
        self.inner.try_lock().map_err(|_| {
            PyRuntimeError::new_err("this Trainer is running (or failed during a run)")
        })
    }
}

/// The initial scene of a point cloud: 3-NN isotropic scales times `scale`, identity rotations,
/// `opacity`, DC colour from `colors` (N,3) in [0, 1], higher SH bands zero.
///
/// Raises:
///     ValueError: an empty or non-finite cloud, bad shapes or values.
#[pyfunction]
#[pyo3(signature = (points, colors, *, opacity, scale, sh_degree))]
fn _fit_init_scene(
    py: Python<'_>,
    points: PyReadonlyArray2<'_, f32>,
    colors: PyReadonlyArray2<'_, f32>,
    opacity: f32,
    scale: f32,
    sh_degree: u8,
) -> PyResult<PyGaussianScene> {
    let (p, c) = (
        points.as_slice().map_err(|_| {
            PyValueError::new_err("points must be a C-contiguous (N,3) float32 array")
        })?,
        colors.as_slice().map_err(|_| {
            PyValueError::new_err("colors must be a C-contiguous (N,3) float32 array")
        })?,
    );
    if sh_degree > 3 {
        return Err(PyValueError::new_err(format!(
            "sh_degree must be 0..=3, got {sh_degree}"
        )));
    }
    let s = detach(py, || {
        init::scene_from_points(p, c, opacity, scale, sh_degree)
    })?;
    PyGaussianScene::from_core(py, s)
}

/// `n` points uniform in the box [lo, hi] and uniform colours, from the counter-based generator
/// (the same for any thread count): (points (N,3), colors (N,3)) float32.
#[pyfunction]
#[pyo3(signature = (n, lo, hi, *, seed))]
fn _fit_random_points<'py>(
    py: Python<'py>,
    n: usize,
    lo: [f32; 3],
    hi: [f32; 3],
    seed: u64,
) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<f32>>)> {
    if n > 100_000_000 {
        return Err(PyValueError::new_err(format!(
            "{n} random points is too many"
        )));
    }
    let (p, c) = py.detach(|| crate::pool::install(|| init::random_points(n, lo, hi, seed)));
    let bad = |e: numpy::ndarray::ShapeError| PyValueError::new_err(e.to_string());
    Ok((
        Array2::from_shape_vec((n, 3), p)
            .map_err(bad)?
            .into_pyarray(py),
        Array2::from_shape_vec((n, 3), c)
            .map_err(bad)?
            .into_pyarray(py),
    ))
}

/// The training loss of a render against its target (both (H,W,3) float32) and its gradient:
/// (loss, l1, ssim, dL/d(render) (H,W,3)). For tests against a reference implementation.
#[pyfunction]
#[pyo3(signature = (render, target, *, ssim_lambda = 0.2))]
fn _fit_loss<'py>(
    py: Python<'py>,
    render: PyReadonlyArray3<'py, f32>,
    target: PyReadonlyArray3<'py, f32>,
    ssim_lambda: f32,
) -> PyResult<(f64, f64, f64, Bound<'py, PyArray3<f32>>)> {
    let sh = render.shape().to_vec();
    if sh.len() != 3 || sh[2] != 3 || target.shape() != sh.as_slice() {
        return Err(PyValueError::new_err(format!(
            "render and target must both be (H,W,3), got {sh:?} and {:?}",
            target.shape()
        )));
    }
    let (r, t) = (
        render
            .as_slice()
            .map_err(|_| PyValueError::new_err("render must be C-contiguous"))?,
        target
            .as_slice()
            .map_err(|_| PyValueError::new_err("target must be C-contiguous"))?,
    );
    let mut g = vec![0.0f32; r.len()];
    let terms = py.detach(|| {
        crate::pool::install(|| {
            fit::loss::LossWorkspace::default().loss_and_grad(
                r,
                t,
                sh[1],
                sh[0],
                ssim_lambda,
                &mut g,
            )
        })
    });
    let arr = Array3::from_shape_vec((sh[0], sh[1], 3), g)
        .map_err(|e| PyValueError::new_err(e.to_string()))?
        .into_pyarray(py);
    Ok((terms.loss, terms.l1, terms.ssim, arr))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyTrainer>()?;
    m.add_function(wrap_pyfunction!(_fit_init_scene, m)?)?;
    m.add_function(wrap_pyfunction!(_fit_random_points, m)?)?;
    m.add_function(wrap_pyfunction!(_fit_loss, m)?)?;
    Ok(())
}
