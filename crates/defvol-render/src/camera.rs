//! Cameras placed by a pose (`world_from_camera`), in the optical convention of ROS
//! (REP 103): x right, y down, z forward.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::RenderError;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum Projection {
    /// Vertical field of view, degrees.
    Perspective { fov_y_deg: f64 },
    /// Height of the view, world units.
    Orthographic { height: f64 },
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub world_from_camera: Isometry3<f64>,
    pub projection: Projection,
    pub width: usize,
    pub height: usize,
}

impl Camera {
    /// A camera at `eye` looking at `target`, `up` pointing up in the picture.
    pub fn look_at(
        eye: Point3<f64>,
        target: Point3<f64>,
        up: Vector3<f64>,
        projection: Projection,
        width: usize,
        height: usize,
    ) -> Result<Self, RenderError> {
        let bad = |why: &str| RenderError::Camera(why.to_owned());
        if !(eye.iter().chain(target.iter()).chain(up.iter()).all(|v| v.is_finite())) {
            return Err(bad("eye, target or up is not finite"));
        }
        let forward = (target - eye).try_normalize(1e-12).ok_or_else(|| bad("eye and target coincide"))?;
        let right =
            forward.cross(&up).try_normalize(1e-9).ok_or_else(|| bad("up is parallel to the view direction"))?;
        let down = forward.cross(&right);
        let rotation = Rotation3::from_basis_unchecked(&[right, down, forward]);
        let camera = Self {
            world_from_camera: Isometry3::from_parts(
                eye.coords.into(),
                UnitQuaternion::from_rotation_matrix(&rotation),
            ),
            projection,
            width,
            height,
        };
        camera.validate()?;
        Ok(camera)
    }

    /// A camera from a pose as a ROS message carries it (position, quaternion x, y, z, w);
    /// a quaternion further than 1e-3 from unit length is refused rather than normalised.
    pub fn from_pose(
        position: [f64; 3],
        quaternion: [f64; 4],
        projection: Projection,
        width: usize,
        height: usize,
    ) -> Result<Self, RenderError> {
        if !position.iter().chain(&quaternion).all(|v| v.is_finite()) {
            return Err(RenderError::Camera("the camera pose has a NaN or infinite value".into()));
        }
        let [x, y, z, w] = quaternion;
        let q = nalgebra::Quaternion::new(w, x, y, z);
        if (q.norm() - 1.0).abs() > 1e-3 {
            return Err(RenderError::Camera(format!("the camera quaternion has length {:.4}, not 1", q.norm())));
        }
        let camera = Self {
            world_from_camera: Isometry3::from_parts(
                Vector3::from(position).into(),
                UnitQuaternion::from_quaternion(q),
            ),
            projection,
            width,
            height,
        };
        camera.validate()?;
        Ok(camera)
    }

    pub fn validate(&self) -> Result<(), RenderError> {
        let bad = |why: String| Err(RenderError::Camera(why));
        if self.width == 0 || self.height == 0 || self.width > 16_384 || self.height > 16_384 {
            return bad(format!("image size {}x{} (1..16384 a side)", self.width, self.height));
        }
        match self.projection {
            Projection::Perspective { fov_y_deg } if !(fov_y_deg > 0.0 && fov_y_deg < 179.0) => {
                bad(format!("field of view {fov_y_deg}° (0..179)"))
            }
            Projection::Orthographic { height } if !(height.is_finite() && height > 0.0) => {
                bad(format!("orthographic height {height}"))
            }
            _ => Ok(()),
        }
    }

    /// The ray through the centre of pixel (px, py): origin and unit direction, world frame.
    pub fn ray(&self, px: usize, py: usize) -> (Point3<f64>, Vector3<f64>) {
        self.rays().ray(px, py)
    }

    /// This camera's rays, what is the same for every pixel worked out once: the field of
    /// view's tangent (a libm call per ray otherwise), and the pose as a matrix (not a
    /// quaternion turning the origin and the direction of every ray; see
    /// docs/perf/journal.md#camera-rays-set-up-once).
    pub fn rays(&self) -> Rays<'_> {
        let aspect = self.width as f64 / self.height as f64;
        let tangent = match self.projection {
            Projection::Perspective { fov_y_deg } => (fov_y_deg.to_radians() / 2.0).tan(),
            Projection::Orthographic { .. } => 0.0,
        };
        let rotation = self.world_from_camera.rotation.to_rotation_matrix().into_inner();
        let eye = Point3::from(self.world_from_camera.translation.vector);
        Rays { camera: self, aspect, tangent, rotation, eye }
    }
}

/// A camera's rays ([`Camera::rays`]): [`Rays::ray`] gives [`Camera::ray`]'s bits.
#[derive(Debug, Clone, Copy)]
pub struct Rays<'a> {
    pub(crate) camera: &'a Camera,
    /// The image's width over its height.
    pub(crate) aspect: f64,
    /// tan(fov_y / 2) for a perspective camera.
    pub(crate) tangent: f64,
    /// The pose as a matrix and the camera's centre, world frame.
    pub(crate) rotation: Matrix3<f64>,
    pub(crate) eye: Point3<f64>,
}

impl Rays<'_> {
    /// Whether the rays leave one eye (a perspective camera), as [`Self::ray`] makes them
    /// from the fields that callers making many at once read (the volume raycaster's
    /// packets, four lanes of f64 at a time).
    pub(crate) fn is_perspective(&self) -> bool {
        matches!(self.camera.projection, Projection::Perspective { .. })
    }

    /// The ray through the centre of pixel (px, py): origin and unit direction, world frame.
    #[inline]
    pub fn ray(&self, px: usize, py: usize) -> (Point3<f64>, Vector3<f64>) {
        let camera = self.camera;
        let u = ((px as f64 + 0.5) / camera.width as f64) * 2.0 - 1.0;
        let v = ((py as f64 + 0.5) / camera.height as f64) * 2.0 - 1.0;
        let (aspect, t) = (self.aspect, self.tangent);
        match camera.projection {
            Projection::Perspective { .. } => {
                (self.eye, self.rotation * Vector3::new(u * t * aspect, v * t, 1.0).normalize())
            }
            Projection::Orthographic { height } => {
                let offset = Vector3::new(u * height / 2.0 * aspect, v * height / 2.0, 0.0);
                (self.eye + self.rotation * offset, self.rotation.column(2).into_owned())
            }
        }
    }
}
