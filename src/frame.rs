//! Vectors and the direction conventions of `docs/conventions.md`: the macro normal is +z, theta is
//! measured from +z, phi from +x towards +y; angles at the command line and in files are degrees.

use std::ops::{Add, Mul, Neg, Sub};

/// A 3-vector of `f64`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Vec3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Vec3 {
    pub const Z: Vec3 = Vec3 {
        x: 0.0,
        y: 0.0,
        z: 1.0,
    };

    pub const fn new(x: f64, y: f64, z: f64) -> Self {
        Vec3 { x, y, z }
    }
    pub fn dot(self, o: Vec3) -> f64 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    pub fn cross(self, o: Vec3) -> Vec3 {
        Vec3::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }
    pub fn norm(self) -> f64 {
        self.dot(self).sqrt()
    }
    /// The unit vector along `self`; the zero vector stays zero.
    pub fn normalized(self) -> Vec3 {
        let n = self.norm();
        if n > 0.0 {
            self * (1.0 / n)
        } else {
            self
        }
    }
    pub fn to_array(self) -> [f64; 3] {
        [self.x, self.y, self.z]
    }
}

impl Add for Vec3 {
    type Output = Vec3;
    fn add(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}
impl Sub for Vec3 {
    type Output = Vec3;
    fn sub(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}
impl Mul<f64> for Vec3 {
    type Output = Vec3;
    fn mul(self, s: f64) -> Vec3 {
        Vec3::new(self.x * s, self.y * s, self.z * s)
    }
}
impl Neg for Vec3 {
    type Output = Vec3;
    fn neg(self) -> Vec3 {
        Vec3::new(-self.x, -self.y, -self.z)
    }
}

/// Unit direction from spherical angles in radians.
pub fn dir_from_rad(theta: f64, phi: f64) -> Vec3 {
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    Vec3::new(st * cp, st * sp, ct)
}

/// Unit direction from spherical angles in degrees (the unit of every file and flag).
pub fn dir_from_deg(theta_deg: f64, phi_deg: f64) -> Vec3 {
    dir_from_rad(theta_deg.to_radians(), phi_deg.to_radians())
}

/// `(theta, phi)` in radians of a unit vector; phi in `[0, 2 pi)`.
pub fn angles_of(w: Vec3) -> (f64, f64) {
    let theta = w.z.clamp(-1.0, 1.0).acos();
    let mut phi = w.y.atan2(w.x);
    if phi < 0.0 {
        phi += std::f64::consts::TAU;
    }
    (theta, phi)
}

/// Rotate a direction about +z by `angle` radians.
pub fn rotate_z(w: Vec3, angle: f64) -> Vec3 {
    let (s, c) = angle.sin_cos();
    Vec3::new(c * w.x - s * w.y, s * w.x + c * w.y, w.z)
}

/// The shortest rotation taking one unit vector onto another (Rodrigues' formula).
#[derive(Debug, Clone, Copy)]
pub struct Rotation {
    axis: Vec3,
    sin: f64,
    cos: f64,
}

impl Rotation {
    /// The rotation taking unit `from` onto unit `to` about their common normal; the identity
    /// when they are parallel or opposite (no unique axis).
    pub fn between(from: Vec3, to: Vec3) -> Self {
        let axis = from.cross(to);
        let sin = axis.norm();
        if sin > 1e-12 {
            Rotation {
                axis: axis * (1.0 / sin),
                sin,
                cos: from.dot(to),
            }
        } else {
            Rotation {
                axis: Vec3::Z,
                sin: 0.0,
                cos: 1.0,
            }
        }
    }

    /// `v` rotated (renormalised against rounding).
    pub fn apply(&self, v: Vec3) -> Vec3 {
        let k = self.axis;
        (v * self.cos + k.cross(v) * self.sin + k * (k.dot(v) * (1.0 - self.cos))).normalized()
    }
}

/// An orthonormal frame `(t, b, n)` around unit `n` (Duff et al. 2017, branchless).
pub fn frame_around(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1f64.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    let t = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
    let bt = Vec3::new(b, sign + n.y * n.y * a, -n.y);
    (t, bt)
}

/// A large-scale direction pair, both unit vectors in the macro frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DirPair {
    pub wi: Vec3,
    pub wo: Vec3,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_between_takes_from_onto_to() {
        let (a, b) = (dir_from_deg(30.0, 20.0), dir_from_deg(70.0, 200.0));
        let r = Rotation::between(a, b);
        assert!((r.apply(a) - b).norm() < 1e-12);
        let c = dir_from_deg(10.0, 80.0);
        assert!(
            (r.apply(c).dot(b) - c.dot(a)).abs() < 1e-12,
            "angles are kept"
        );
        let same = Rotation::between(a, a);
        assert!((same.apply(c) - c).norm() < 1e-12);
    }

    #[test]
    fn angles_round_trip() {
        for &(t, p) in &[(0.0, 0.0), (30.0, 45.0), (89.9, 359.0), (60.0, 180.0)] {
            let w = dir_from_deg(t, p);
            let (tt, pp) = angles_of(w);
            assert!((tt.to_degrees() - t).abs() < 1e-9);
            if t > 0.0 {
                assert!((pp.to_degrees() - p).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn frame_is_orthonormal() {
        for n in [
            Vec3::Z,
            Vec3::new(0.0, 0.0, -1.0),
            Vec3::new(0.3, -0.4, 0.866).normalized(),
        ] {
            let (t, b) = frame_around(n);
            assert!(t.dot(b).abs() < 1e-12 && t.dot(n).abs() < 1e-12 && b.dot(n).abs() < 1e-12);
            assert!((t.cross(b).dot(n) - 1.0).abs() < 1e-12);
        }
    }
}
