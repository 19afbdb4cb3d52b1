//! View-dependent visibility: each Gaussian may be hidden from the cameras whose direction to
//! it falls inside a cone (a cap on the sphere of directions), the rendering half of the
//! sparse-view "popping" corruption (`perturb::popping` draws the caps).
//!
//! Gaussian `i` with axis `a_i` (unit) and cap height `h_i` in [0, 2] is hidden from a camera
//! centred at `c` iff `h_i > 0` and `dot(unit(mu_i - c), a_i) > 1 - h_i`: a cone of half-angle
//! `acos(1 - h_i)` around `a_i`. `h_i = 0` never hides. The test depends on the camera centre
//! only, so one camera always gives one visibility (a revisited view renders the same frame),
//! and it uses only exactly rounded operations (the same bits on every CPU). A hidden Gaussian
//! is rendered as if absent: its opacity logit becomes -inf, which projection culls, so the
//! frame equals a render of the scene without it.
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::scene::SceneView;

/// The names of the scene extras that carry caps: a scene holding all four renders with them
/// (the axis' x, y, z and the cap height `h`).
pub const EXTRAS: [&str; 4] = ["popping_x", "popping_y", "popping_z", "popping_h"];

/// The caps of one scene's Gaussians, structure of arrays (each as long as the scene).
#[derive(Debug, Clone, Copy)]
pub struct Caps<'a> {
    pub axis: [&'a [f32]; 3],
    pub h: &'a [f32],
}

/// A camera's centre in world space, rounded to f32 as the scene's means are.
pub fn centre(cam: &Camera) -> [f32; 3] {
    cam.center().map(|v| v as f32)
}

/// The unit direction from `from` to `to` (None when they coincide or it is not finite).
#[inline]
pub fn direction(from: [f32; 3], to: [f32; 3]) -> Option<[f32; 3]> {
    let d = [to[0] - from[0], to[1] - from[1], to[2] - from[2]];
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    (n.is_finite() && n > 0.0).then(|| [d[0] / n, d[1] / n, d[2] / n])
}

impl<'a> Caps<'a> {
    /// Caps from the four extras of a scene (in [`EXTRAS`] order).
    pub fn of(x: &'a [f32], y: &'a [f32], z: &'a [f32], h: &'a [f32]) -> Self {
        Caps { axis: [x, y, z], h }
    }

    /// Check the lengths against a scene of `n` Gaussians and every height (finite, in [0, 2]).
    pub fn validate(&self, n: usize) -> Result<()> {
        for (name, v) in EXTRAS
            .iter()
            .zip([self.axis[0], self.axis[1], self.axis[2], self.h])
        {
            if v.len() != n {
                return Err(Error::InvalidArgument(format!(
                    "{name} holds {} values, expected one per Gaussian ({n})",
                    v.len()
                )));
            }
        }
        if let Some((i, h)) = self
            .h
            .iter()
            .enumerate()
            .find(|(_, h)| !(0.0..=2.0).contains(*h))
        {
            return Err(Error::InvalidArgument(format!(
                "popping_h[{i}] must be a cap height in [0, 2], got {h}"
            )));
        }
        Ok(())
    }

    /// Whether Gaussian `i` at `mu` is hidden from a camera centred at `centre`.
    #[inline]
    pub fn hides(&self, i: usize, mu: [f32; 3], centre: [f32; 3]) -> bool {
        let h = self.h[i];
        if h <= 0.0 {
            return false;
        }
        let Some(d) = direction(centre, mu) else {
            return false;
        };
        let a = [self.axis[0][i], self.axis[1][i], self.axis[2][i]];
        d[0] * a[0] + d[1] * a[1] + d[2] * a[2] > 1.0 - h
    }

    /// `scene`'s opacity logits as a camera at `centre` sees them: -inf for the hidden
    /// Gaussians, the scene's own elsewhere (written into `out`, resized to the scene).
    pub fn logits(&self, scene: &SceneView<'_>, centre: [f32; 3], out: &mut Vec<f32>) {
        out.clear();
        out.extend(scene.opacity_logits.iter().enumerate().map(|(i, &l)| {
            let m = &scene.means[i * 3..i * 3 + 3];
            if self.hides(i, [m[0], m[1], m[2]], centre) {
                f32::NEG_INFINITY
            } else {
                l
            }
        }));
    }

    /// How many of `scene`'s Gaussians a camera at `centre` does not see.
    pub fn hidden_count(&self, scene: &SceneView<'_>, centre: [f32; 3]) -> usize {
        (0..scene.len())
            .filter(|&i| {
                let m = &scene.means[i * 3..i * 3 + 3];
                self.hides(i, [m[0], m[1], m[2]], centre)
            })
            .count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cap_hides_inside_its_cone_only() {
        let (x, y, z, h) = (
            [1.0f32, 1.0, 1.0],
            [0.0f32; 3],
            [0.0f32; 3],
            [0.5f32, 0.0, 2.0],
        );
        let caps = Caps::of(&x, &y, &z, &h);
        caps.validate(3).expect("valid");
        // looking along +x at the Gaussian: inside every cap with h > 0
        let (mu, behind) = ([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]);
        assert!(caps.hides(0, mu, behind));
        assert!(!caps.hides(1, mu, behind), "h = 0 never hides");
        // from the side (90 degrees off the axis; cap 0 reaches 60 degrees)
        assert!(!caps.hides(0, mu, [1.0, -1.0, 0.0]));
        assert!(
            caps.hides(0, mu, [0.5, -0.5, 0.0]),
            "45 degrees off the axis"
        );
        assert!(
            caps.hides(2, mu, [3.0, 0.1, 0.0]),
            "h = 2 hides from all but -a"
        );
        assert!(!caps.hides(0, mu, mu), "a camera at the Gaussian sees it");
    }

    #[test]
    fn bad_caps_are_named() {
        let v = [0.0f32; 2];
        let e = Caps::of(&v, &v, &v[..1], &v)
            .validate(2)
            .expect_err("length");
        assert!(e.to_string().contains("popping_z"), "{e}");
        let h = [0.0, 2.5];
        let e = Caps::of(&v, &v, &v, &h).validate(2).expect_err("height");
        assert!(e.to_string().contains("popping_h[1]"), "{e}");
    }
}
