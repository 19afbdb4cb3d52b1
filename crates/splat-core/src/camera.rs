//! Pinhole cameras in the OpenCV convention (SPEC §3): x right, y down, z forward.
//!
//! A camera is intrinsics (fx, fy, cx, cy), an image size and a world-to-camera 4x4 matrix
//! (p_c = R p_w + t). Pixel (i, j) has its centre at (j + 0.5, i + 0.5).
use crate::error::{Error, Result};

/// Largest accepted image side, in pixels (keeps a typo from allocating terabytes).
pub const MAX_IMAGE_SIDE: u32 = 1 << 15;

/// One pinhole camera. Values are float64 as given by the caller; the rasterizer works in float32.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    /// Row-major world-to-camera matrix; the last row is expected to be (0, 0, 0, 1).
    pub world_to_camera: [[f64; 4]; 4],
    pub near: f64,
    pub far: f64,
}

impl Camera {
    /// A camera with the default clipping planes (near 0.01, far 1e10).
    pub fn new(
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        width: u32,
        height: u32,
        world_to_camera: [[f64; 4]; 4],
    ) -> Self {
        Camera {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            world_to_camera,
            near: 0.01,
            far: 1e10,
        }
    }

    /// Build from row-major 4x4 world-to-camera and 3x3 intrinsic matrices.
    pub fn from_matrices(
        world_to_camera: &[f64],
        k: &[f64],
        width: u32,
        height: u32,
        near: f64,
        far: f64,
    ) -> Result<Self> {
        if world_to_camera.len() != 16 || k.len() != 9 {
            return Err(Error::InvalidArgument(format!(
                "camera matrices must hold 16 and 9 values, got {} and {}",
                world_to_camera.len(),
                k.len()
            )));
        }
        let mut m = [[0.0; 4]; 4];
        for (r, row) in m.iter_mut().enumerate() {
            row.copy_from_slice(&world_to_camera[r * 4..r * 4 + 4]);
        }
        let cam = Camera {
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
            width,
            height,
            world_to_camera: m,
            near,
            far,
        };
        cam.validate()?;
        Ok(cam)
    }

    /// Check that every value is finite, focal lengths positive, the size non-zero and bounded,
    /// and 0 < near < far.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| Err(Error::InvalidArgument(msg));
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "image size must be positive, got {}x{}",
                self.width, self.height
            ));
        }
        if self.width > MAX_IMAGE_SIDE || self.height > MAX_IMAGE_SIDE {
            return bad(format!(
                "image size {}x{} exceeds the limit of {MAX_IMAGE_SIDE} pixels per side",
                self.width, self.height
            ));
        }
        let intr = [self.fx, self.fy, self.cx, self.cy];
        if !intr.iter().all(|v| v.is_finite()) {
            return bad(format!(
                "camera intrinsics must be finite, got fx={} fy={} cx={} cy={}",
                self.fx, self.fy, self.cx, self.cy
            ));
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return bad(format!(
                "focal lengths must be positive, got fx={} fy={}",
                self.fx, self.fy
            ));
        }
        if !self.world_to_camera.iter().flatten().all(|v| v.is_finite()) {
            return bad("world_to_camera holds NaN or Inf values".to_owned());
        }
        if !(self.near.is_finite() && self.near > 0.0 && self.far > self.near) {
            return bad(format!(
                "need 0 < near < far, got near={} far={}",
                self.near, self.far
            ));
        }
        Ok(())
    }

    /// Rotation part R of the world-to-camera matrix.
    pub fn rotation(&self) -> [[f64; 3]; 3] {
        let m = &self.world_to_camera;
        [
            [m[0][0], m[0][1], m[0][2]],
            [m[1][0], m[1][1], m[1][2]],
            [m[2][0], m[2][1], m[2][2]],
        ]
    }

    /// Translation part t of the world-to-camera matrix.
    pub fn translation(&self) -> [f64; 3] {
        let m = &self.world_to_camera;
        [m[0][3], m[1][3], m[2][3]]
    }

    /// Camera centre in world coordinates, -R^T t (the matrix is taken as rigid).
    pub fn center(&self) -> [f64; 3] {
        let r = self.rotation();
        let t = self.translation();
        let mut c = [0.0; 3];
        for (i, ci) in c.iter_mut().enumerate() {
            *ci = -(r[0][i] * t[0] + r[1][i] * t[1] + r[2][i] * t[2]);
        }
        c
    }

    /// Number of 16x16 tiles across and down.
    pub fn tiles(&self) -> (u32, u32) {
        (self.width.div_ceil(16), self.height.div_ceil(16))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn identity() -> [[f64; 4]; 4] {
        let mut m = [[0.0; 4]; 4];
        for (i, row) in m.iter_mut().enumerate() {
            row[i] = 1.0;
        }
        m
    }

    #[test]
    fn validate_rejects_zero_size_and_non_finite_values() {
        let ok = Camera::new(100.0, 100.0, 32.0, 24.0, 64, 48, identity());
        assert!(ok.validate().is_ok());
        assert!(Camera { width: 0, ..ok }.validate().is_err());
        assert!(Camera { fx: f64::NAN, ..ok }.validate().is_err());
        assert!(Camera { fy: -1.0, ..ok }.validate().is_err());
        let mut m = identity();
        m[1][3] = f64::INFINITY;
        assert!(Camera {
            world_to_camera: m,
            ..ok
        }
        .validate()
        .is_err());
        assert!(Camera { near: 2e10, ..ok }.validate().is_err());
    }

    #[test]
    fn center_inverts_the_rigid_transform() {
        let mut m = identity();
        // rotate 90 degrees about z, then translate
        m[0] = [0.0, -1.0, 0.0, 1.0];
        m[1] = [1.0, 0.0, 0.0, 2.0];
        m[2] = [0.0, 0.0, 1.0, 3.0];
        let cam = Camera::new(1.0, 1.0, 0.0, 0.0, 1, 1, m);
        let c = cam.center();
        // R c + t must be zero
        let r = cam.rotation();
        for i in 0..3 {
            let v = r[i][0] * c[0] + r[i][1] * c[1] + r[i][2] * c[2] + cam.translation()[i];
            assert!(v.abs() < 1e-12);
        }
    }
}
