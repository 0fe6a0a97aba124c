//! Procedural object-centric scenes: a few deformed shapes with solid procedural textures on a
//! textured ground, a sky at infinity, simple Lambert shading; and CO3D-like camera paths.

use std::f64::consts::{PI, TAU};

use nalgebra::{Matrix3, Rotation3, Vector3};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::noise::{fbm, value};
use crate::render::{Buffers, Triangle};

/// Shape families.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// Unit sphere.
    Sphere,
    /// Unit cube `[−1, 1]³`.
    Box,
    /// Torus of radii 1 and `tube`.
    Torus {
        /// Tube radius.
        tube: f64,
    },
    /// Superquadric with exponents `e1` (latitude) and `e2` (longitude).
    Superquadric {
        /// Latitude exponent.
        e1: f64,
        /// Longitude exponent.
        e2: f64,
    },
}

/// Surface patterns mixed into the noise.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pattern {
    /// Noise only.
    Noise,
    /// Wavy stripes.
    Stripes,
    /// A 3-D checkerboard.
    Checker,
    /// Thresholded noise blobs.
    Spots,
}

/// A solid procedural material.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Main colour (linear, 0–1).
    pub base: [f64; 3],
    /// Second colour.
    pub accent: [f64; 3],
    /// The pattern.
    pub pattern: Pattern,
    /// Spatial frequency of the pattern and noise (per world unit).
    pub frequency: f64,
    /// Noise seed.
    pub seed: u64,
}

impl Material {
    /// A material drawn from `rng`: pattern, colours and noise at `frequency`.
    pub fn random(rng: &mut StdRng, frequency: f64) -> Self {
        let colour = |rng: &mut StdRng| [0, 1, 2].map(|_| rng.random_range(0.1..0.95));
        let pattern = match rng.random_range(0..4) {
            0 => Pattern::Noise,
            1 => Pattern::Stripes,
            2 => Pattern::Checker,
            _ => Pattern::Spots,
        };
        Self {
            base: colour(rng),
            accent: colour(rng),
            pattern,
            frequency,
            seed: rng.random(),
        }
    }

    /// The colour at world point `p`.
    pub fn colour(&self, p: &Vector3<f64>) -> [f64; 3] {
        let q = p * self.frequency;
        let n = fbm(&q, 5, 0.55, self.seed);
        let fine = value(&(q * 8.0), self.seed ^ 0xABCD);
        let mix = match self.pattern {
            Pattern::Noise => n,
            Pattern::Stripes => 0.5 + 0.5 * (q.x * 2.0 + q.z * 1.3 + 6.0 * n).sin(),
            Pattern::Checker => {
                let c = (q.x.floor() + q.y.floor() + q.z.floor()).rem_euclid(2.0);
                0.7 * c + 0.3 * n
            }
            Pattern::Spots => {
                if value(&(q * 1.5), self.seed ^ 0x5150) > 0.6 {
                    0.9
                } else {
                    0.2 * n
                }
            }
        };
        let m = mix.clamp(0.0, 1.0);
        [0, 1, 2].map(|c| {
            let v = self.base[c] * (1.0 - m) + self.accent[c] * m;
            (v * (0.8 + 0.4 * fine)).clamp(0.0, 1.0)
        })
    }
}

/// One object: a shape in its own frame, deformed, scaled, rotated and placed.
#[derive(Debug, Clone, PartialEq)]
pub struct Object {
    /// Shape family.
    pub shape: Shape,
    /// Position of its centre.
    pub center: Vector3<f64>,
    /// Per-axis half extents.
    pub scale: Vector3<f64>,
    /// Orientation.
    pub rotation: Rotation3<f64>,
    /// Radial displacement amplitude (fraction of the size) and its noise frequency.
    pub deformation: (f64, f64),
    /// Surface material.
    pub material: Material,
}

/// A whole scene.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The objects (material index = position; the ground comes after them).
    pub objects: Vec<Object>,
    /// The ground plane's material (`z = 0`).
    pub ground: Material,
    /// Seed of the sky.
    pub sky_seed: u64,
    /// Direction towards the light (unit).
    pub light: Vector3<f64>,
    /// Where the cameras look: the objects' centroid.
    pub target: Vector3<f64>,
    /// Radius of a sphere around `target` holding the objects.
    pub radius: f64,
    /// Everything as triangles.
    pub triangles: Vec<Triangle>,
}

/// Grid resolution of the parametric surfaces.
const GRID: usize = 48;
/// Half size of the ground square.
const GROUND_HALF: f64 = 30.0;

fn signed_pow(x: f64, e: f64) -> f64 {
    x.signum() * x.abs().powf(e)
}

/// Points of a shape's parametric grid (object frame) and its quads as index quadruples.
fn parametric(shape: Shape) -> (Vec<Vector3<f64>>, Vec<[usize; 4]>) {
    let mut points = Vec::new();
    let mut quads = Vec::new();
    let grid = |f: &dyn Fn(f64, f64) -> Vector3<f64>,
                points: &mut Vec<Vector3<f64>>,
                quads: &mut Vec<[usize; 4]>| {
        let base = points.len();
        for i in 0..=GRID {
            for j in 0..=GRID {
                points.push(f(i as f64 / GRID as f64, j as f64 / GRID as f64));
            }
        }
        for i in 0..GRID {
            for j in 0..GRID {
                let a = base + i * (GRID + 1) + j;
                quads.push([a, a + 1, a + GRID + 2, a + GRID + 1]);
            }
        }
    };
    match shape {
        Shape::Sphere => grid(
            &|u, v| {
                let (th, ph) = (TAU * u, PI * v);
                Vector3::new(th.cos() * ph.sin(), th.sin() * ph.sin(), ph.cos())
            },
            &mut points,
            &mut quads,
        ),
        Shape::Superquadric { e1, e2 } => grid(
            &|u, v| {
                let (th, ph) = (TAU * u - PI, PI * v - PI / 2.0);
                Vector3::new(
                    signed_pow(ph.cos(), e1) * signed_pow(th.cos(), e2),
                    signed_pow(ph.cos(), e1) * signed_pow(th.sin(), e2),
                    signed_pow(ph.sin(), e1),
                )
            },
            &mut points,
            &mut quads,
        ),
        Shape::Torus { tube } => grid(
            &|u, v| {
                let (th, ph) = (TAU * u, TAU * v);
                Vector3::new(
                    (1.0 + tube * ph.cos()) * th.cos(),
                    (1.0 + tube * ph.cos()) * th.sin(),
                    tube * ph.sin(),
                )
            },
            &mut points,
            &mut quads,
        ),
        Shape::Box => {
            // Six faces: a fixed axis at ±1, the other two over [−1, 1].
            for axis in 0..3 {
                for side in [-1.0, 1.0] {
                    grid(
                        &|u, v| {
                            let mut p = Vector3::zeros();
                            p[axis] = side;
                            p[(axis + 1) % 3] = 2.0 * u - 1.0;
                            p[(axis + 2) % 3] = 2.0 * v - 1.0;
                            p
                        },
                        &mut points,
                        &mut quads,
                    );
                }
            }
        }
    }
    (points, quads)
}

impl Object {
    /// The object's triangles in world coordinates.
    pub fn triangles(&self, id: u32) -> Vec<Triangle> {
        let (points, quads) = parametric(self.shape);
        let (amp, freq) = self.deformation;
        let world: Vec<Vector3<f64>> = points
            .iter()
            .map(|p| {
                let radial = if p.norm() > 0.0 { p.normalize() } else { *p };
                let d = amp * (fbm(&(p * freq), 3, 0.5, self.material.seed ^ 0xD3F0) - 0.5);
                let q = p + radial * d;
                self.center + self.rotation * q.component_mul(&self.scale)
            })
            .collect();
        quads
            .iter()
            .flat_map(|q| {
                [
                    Triangle {
                        v: [world[q[0]], world[q[1]], world[q[2]]],
                        object: id,
                    },
                    Triangle {
                        v: [world[q[0]], world[q[2]], world[q[3]]],
                        object: id,
                    },
                ]
            })
            .collect()
    }
}

impl Scene {
    /// A random scene: 1–3 objects of random shapes, sizes, deformations and materials.
    pub fn random(seed: u64) -> Self {
        let mut rng = StdRng::seed_from_u64(seed);
        let count = rng.random_range(1..=3usize);
        let mut objects = Vec::with_capacity(count);
        for k in 0..count {
            let shape = match rng.random_range(0..4) {
                0 => Shape::Sphere,
                1 => Shape::Box,
                2 => Shape::Torus {
                    tube: rng.random_range(0.25..0.5),
                },
                _ => Shape::Superquadric {
                    e1: rng.random_range(0.3..1.8),
                    e2: rng.random_range(0.3..1.8),
                },
            };
            let size = rng.random_range(0.5..1.0);
            let scale = Vector3::new(
                size * rng.random_range(0.7..1.3),
                size * rng.random_range(0.7..1.3),
                size * rng.random_range(0.6..1.4),
            );
            let angle = TAU * k as f64 / count as f64 + rng.random_range(0.0..1.0);
            let offset = if count == 1 {
                0.0
            } else {
                rng.random_range(0.8..1.3)
            };
            let lift = match shape {
                Shape::Torus { tube } => tube * scale.z,
                _ => scale.z,
            };
            objects.push(Object {
                shape,
                center: Vector3::new(offset * angle.cos(), offset * angle.sin(), lift * 0.9),
                scale,
                rotation: Rotation3::from_euler_angles(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    rng.random_range(0.0..TAU),
                ),
                deformation: (rng.random_range(0.0..0.35), rng.random_range(1.0..3.0)),
                material: {
                    let frequency = rng.random_range(2.0..6.0);
                    Material::random(&mut rng, frequency)
                },
            });
        }
        let ground_frequency = rng.random_range(1.0..3.0);
        let ground = Material::random(&mut rng, ground_frequency);
        let target = objects.iter().map(|o| o.center).sum::<Vector3<f64>>() / count as f64;
        let radius = objects
            .iter()
            .map(|o| (o.center - target).norm() + o.scale.max() * 1.3)
            .fold(0.0, f64::max);
        let mut triangles: Vec<Triangle> = objects
            .iter()
            .enumerate()
            .flat_map(|(i, o)| o.triangles(i as u32))
            .collect();
        let g = |x: f64, y: f64| Vector3::new(x, y, 0.0);
        let ground_id = count as u32;
        triangles.push(Triangle {
            v: [
                g(-GROUND_HALF, -GROUND_HALF),
                g(GROUND_HALF, -GROUND_HALF),
                g(GROUND_HALF, GROUND_HALF),
            ],
            object: ground_id,
        });
        triangles.push(Triangle {
            v: [
                g(-GROUND_HALF, -GROUND_HALF),
                g(GROUND_HALF, GROUND_HALF),
                g(-GROUND_HALF, GROUND_HALF),
            ],
            object: ground_id,
        });
        let light = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(0.8..1.5),
        )
        .normalize();
        Self {
            objects,
            ground,
            sky_seed: rng.random(),
            light,
            target,
            radius,
            triangles,
        }
    }

    fn material(&self, object: u32) -> &Material {
        self.objects
            .get(object as usize)
            .map_or(&self.ground, |o| &o.material)
    }

    /// Shades rasterised hits into 8-bit RGB (row-major); background pixels show the sky in
    /// the direction of their ray.
    pub fn shade(&self, buffers: &Buffers, camera: &Camera) -> Vec<u8> {
        let mut rgb = Vec::with_capacity(buffers.width * buffers.height * 3);
        let k_inv = camera.intrinsics.inverse_matrix();
        let rt = camera.cam_from_world.rotation.transpose();
        for y in 0..buffers.height {
            for x in 0..buffers.width {
                let colour = match buffers.at(x, y) {
                    Some(hit) => {
                        let base = self.material(hit.object).colour(&hit.world);
                        let light = 0.35 + 0.65 * hit.normal.dot(&self.light).max(0.0);
                        base.map(|c| c * light)
                    }
                    None => {
                        let d = rt * (k_inv * Vector3::new(x as f64, y as f64, 1.0));
                        self.sky(&d.normalize())
                    }
                };
                rgb.extend(colour.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8));
            }
        }
        rgb
    }

    fn sky(&self, d: &Vector3<f64>) -> [f64; 3] {
        let up = d.z.clamp(-1.0, 1.0);
        let clouds = fbm(&(d * 4.0), 5, 0.5, self.sky_seed);
        let t = 0.5 + 0.5 * up;
        [
            0.55 * (1.0 - t) + 0.35 * t + 0.35 * clouds,
            0.6 * (1.0 - t) + 0.5 * t + 0.3 * clouds,
            0.65 * (1.0 - t) + 0.8 * t + 0.2 * clouds,
        ]
    }
}

/// An OpenCV camera at `centre` looking at `target` with world `+z` up and `roll` radians.
pub fn look_at(centre: Vector3<f64>, target: Vector3<f64>, roll: f64) -> Pose {
    let z = (target - centre).normalize();
    let mut x = z.cross(&Vector3::z());
    if x.norm() < 1e-9 {
        x = Vector3::x();
    }
    let x = x.normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let r = Rotation3::from_axis_angle(&Vector3::z_axis(), roll).matrix() * r;
    Pose::from_rotation_centre(r, centre)
}

/// Cameras of one sequence: a fly-around (radius, elevation, start angle, speed and direction
/// random, with slow wobble) or, with probability 1/4, a forward approach; focal length from a
/// horizontal field of view of 40–75° across the longer side; principal point at the centre.
pub fn trajectory(scene: &Scene, frames: usize, size: ImageSize, seed: u64) -> Vec<Camera> {
    trajectory_with(scene, frames, size, seed, None)
}

/// A camera path of a sequence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PathKind {
    /// A fly-around (orbit) with slow wobble.
    Orbit,
    /// A forward approach drifting sideways.
    Forward,
}

/// [`trajectory`] with the path kind forced (`None`: drawn, as [`trajectory`]). The random
/// draws are the same either way, so a forced kind equal to the drawn one gives the same path.
pub fn trajectory_with(
    scene: &Scene,
    frames: usize,
    size: ImageSize,
    seed: u64,
    kind: Option<PathKind>,
) -> Vec<Camera> {
    let mut rng = StdRng::seed_from_u64(seed);
    let long = f64::from(size.width().max(size.height()));
    let fov = rng.random_range(40f64..75.0).to_radians();
    let f = long / 2.0 / (fov / 2.0).tan();
    let k = match Intrinsics::new(
        f,
        f,
        (f64::from(size.width()) - 1.0) / 2.0,
        (f64::from(size.height()) - 1.0) / 2.0,
    ) {
        Ok(k) => k,
        Err(_) => unreachable!("positive focal"),
    };
    // Far enough that the objects fill about half the shorter side or more.
    let short = f64::from(size.width().min(size.height()));
    let distance = scene.radius * f / (0.55 * short) * rng.random_range(0.85..1.2);
    let elevation = rng.random_range(12f64..45.0).to_radians();
    let start = rng.random_range(0.0..TAU);
    let arc = rng.random_range(100f64..360.0).to_radians()
        * if rng.random_bool(0.5) { 1.0 } else { -1.0 };
    let drawn = rng.random_bool(0.25);
    let forward = match kind {
        None => drawn,
        Some(k) => k == PathKind::Forward,
    };
    let wobble = rng.random_range(0.0..TAU);
    let jitter = Vector3::new(
        rng.random_range(-0.1..0.1),
        rng.random_range(-0.1..0.1),
        rng.random_range(-0.05..0.05),
    ) * scene.radius;
    let roll = rng.random_range(-0.08..0.08);
    (0..frames)
        .map(|i| {
            let s = if frames > 1 {
                i as f64 / (frames - 1) as f64
            } else {
                0.0
            };
            let (centre, target) = if forward {
                // Approach from 1.6× to 0.9× the distance, drifting sideways.
                let a = start + 0.4 * (s - 0.5) * (wobble.sin());
                let d = distance * (1.6 - 0.7 * s);
                let dir = Vector3::new(
                    elevation.cos() * a.cos(),
                    elevation.cos() * a.sin(),
                    elevation.sin(),
                );
                let side =
                    Vector3::new(-a.sin(), a.cos(), 0.0) * (0.3 * scene.radius * (TAU * s).sin());
                (scene.target + dir * d + side, scene.target + jitter)
            } else {
                let a = start + arc * s;
                let e = elevation + 0.08 * (TAU * s + wobble).sin();
                let d = distance * (1.0 + 0.08 * (2.0 * TAU * s + wobble).cos());
                let dir = Vector3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
                (scene.target + dir * d, scene.target + jitter)
            };
            Camera::new(k, look_at(centre, target, roll), size)
        })
        .collect()
}
