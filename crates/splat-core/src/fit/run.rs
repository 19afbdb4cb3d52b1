//! The optimiser loop: steps until a target, held-out evaluation every `eval_every` steps,
//! checkpoints every `checkpoint_every` steps and when the caller stops the run, with the caller
//! told about each event through [`Hooks`] (a progress bar, CSV rows, Ctrl-C).
//!
//! Order at a completed step s: the step's record; then, when due, the held-out evaluation
//! (per-view records, then the summary); then, when due, `BeforeCheckpoint` (the caller flushes
//! what it logged up to s), the checkpoint write and `Checkpoint`. So whatever a caller logged
//! before a checkpoint is never ahead of it, and a resumed run rewrites exactly the rows after
//! it.
use std::path::PathBuf;

use crate::error::Result;

use super::checkpoint;
use super::trainer::{EvalView, StepRecord, Trainer};

/// What happened; see the module docs for the order.
#[derive(Debug)]
pub enum Event<'a> {
    Step(&'a StepRecord),
    /// One held-out view scored at `step`, with its render (H*W*3).
    EvalView {
        step: u32,
        view: usize,
        metrics: EvalView,
        rgb: &'a [f32],
        width: u32,
        height: u32,
    },
    /// All held-out views scored: mean PSNR and SSIM.
    Eval {
        step: u32,
        psnr: f64,
        ssim: f64,
    },
    BeforeCheckpoint {
        step: u32,
    },
    Checkpoint {
        step: u32,
    },
}

/// Continue, or stop after writing a checkpoint.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flow {
    Continue,
    Stop,
}

/// The caller's side of the loop.
pub trait Hooks {
    /// Run `work` (one step, an evaluation): a binding runs it inside its thread pool.
    fn parallel(&mut self, work: &mut (dyn FnMut() + Send)) {
        work()
    }
    fn event(&mut self, e: Event<'_>) -> Flow;
}

/// When to stop, evaluate and checkpoint.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Stop when this many steps are done (at most the config's steps).
    pub until: u32,
    /// Evaluate every this many steps (0: never) and at the end.
    pub eval_every: u32,
    pub checkpoint: Option<PathBuf>,
    /// Checkpoint every this many steps (0: only at the end and on stop).
    pub checkpoint_every: u32,
    /// The run's identity stored in checkpoints (config and data).
    pub fingerprint: Vec<u8>,
}

/// How the loop ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunEnd {
    /// The target step was reached.
    Finished,
    /// A hook asked to stop (a checkpoint was written when a path was given).
    Stopped,
}

fn evaluate(t: &mut Trainer, hooks: &mut dyn Hooks) -> Result<Flow> {
    let step = t.step();
    let mut flow = Flow::Continue;
    let mut views: Vec<(EvalView, Vec<f32>)> = Vec::new();
    let mut res = Ok(Vec::new());
    hooks.parallel(&mut || {
        res = t.evaluate(|_, e, rgb| views.push((*e, rgb.to_vec())));
    });
    let all = res?;
    for (i, (m, rgb)) in views.iter().enumerate() {
        let cam = &t.eval_views()[i].cam;
        if hooks.event(Event::EvalView {
            step,
            view: i,
            metrics: *m,
            rgb,
            width: cam.width,
            height: cam.height,
        }) == Flow::Stop
        {
            flow = Flow::Stop;
        }
    }
    if !all.is_empty() {
        let n = all.len() as f64;
        let psnr = all.iter().map(|e| e.psnr).sum::<f64>() / n;
        let ssim = all.iter().map(|e| e.ssim).sum::<f64>() / n;
        if hooks.event(Event::Eval { step, psnr, ssim }) == Flow::Stop {
            flow = Flow::Stop;
        }
    }
    Ok(flow)
}

fn save(t: &mut Trainer, opts: &RunOptions, hooks: &mut dyn Hooks) -> Result<Flow> {
    let Some(path) = &opts.checkpoint else {
        return Ok(Flow::Continue);
    };
    let step = t.step();
    let mut flow = hooks.event(Event::BeforeCheckpoint { step });
    let ck = t.checkpoint(&opts.fingerprint);
    let mut res = Ok(());
    hooks.parallel(&mut || res = checkpoint::save(path, &ck));
    res?;
    if hooks.event(Event::Checkpoint { step }) == Flow::Stop {
        flow = Flow::Stop;
    }
    Ok(flow)
}

/// Step `t` until `opts.until` (or a hook stops it).
pub fn run(t: &mut Trainer, opts: &RunOptions, hooks: &mut dyn Hooks) -> Result<RunEnd> {
    let until = opts.until.min(t.config().steps);
    while t.step() < until {
        let mut res = None;
        hooks.parallel(&mut || res = Some(t.step_once()));
        let rec = match res {
            Some(r) => r?,
            None => continue,
        };
        let s = rec.step;
        let mut stop = hooks.event(Event::Step(&rec)) == Flow::Stop;
        let last = s == until;
        let eval_due = opts.eval_every > 0 && (last || s.is_multiple_of(opts.eval_every));
        if eval_due && !t.eval_views().is_empty() {
            stop |= evaluate(t, hooks)? == Flow::Stop;
        }
        let due = opts.checkpoint_every > 0 && s.is_multiple_of(opts.checkpoint_every);
        if due || last || stop {
            stop |= save(t, opts, hooks)? == Flow::Stop;
        }
        if stop && !last {
            return Ok(RunEnd::Stopped);
        }
    }
    Ok(RunEnd::Finished)
}
