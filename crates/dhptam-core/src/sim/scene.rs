//! The simulated world: a textured room seen from inside, with axis-aligned textured boxes
//! (a desk, objects on it, furniture) and photographs hung on the walls and faces.
//!
//! World frame: z up, metres. Every solid is an axis-aligned box, so a ray is intersected
//! analytically with the slab method (three divisions shared by all boxes, a handful of
//! multiplications and comparisons per box); with a few dozen boxes no acceleration
//! structure pays for itself.
//!
//! Texture coordinates on a face are metres in the face's own frame: on vertical faces `u`
//! runs to the right and `v` downwards for a viewer facing the face, on horizontal faces
//! `u = x`, `v = y` (measured from the face's corner). Photographs are decals: rectangles in
//! those coordinates, flush with the face, that replace the face's own texture.

use nalgebra::Vector3;

use super::texture::{Texture, Wrap};
use crate::error::{Error, Result};

/// How a face (or decal) is textured.
#[derive(Clone, Copy, Debug)]
pub struct Surface {
    /// Index into [`Scene::textures`].
    pub texture: usize,
    /// Metres covered by one copy of the texture along `u` and `v`.
    pub tile_m: [f32; 2],
    /// Tiled or clamped.
    pub wrap: Wrap,
    /// Reflectance scale (stands in for shading: faces of one box differ in brightness).
    pub gain: f32,
}

/// A photograph flush with a face: the rectangle `[u0, u1] × [v0, v1]` in face metres.
#[derive(Clone, Copy, Debug)]
pub struct Decal {
    /// Face-coordinate rectangle `[u0, v0, u1, v1]`, metres.
    pub rect: [f32; 4],
    /// Texture index and gain (the tile size is the rectangle; wrap is ignored).
    pub surface: Surface,
}

/// One face of a box: its surface and the decals on it.
#[derive(Clone, Debug)]
pub struct Face {
    /// The texture of the face outside the decals.
    pub surface: Surface,
    /// Photographs on the face.
    pub decals: Vec<Decal>,
}

/// An axis-aligned box. Faces are indexed `2·axis + side`, side 0 at `min`, 1 at `max`.
#[derive(Clone, Debug)]
pub struct SceneBox {
    /// Lower corner, metres.
    pub min: [f32; 3],
    /// Upper corner, metres.
    pub max: [f32; 3],
    /// The six faces.
    pub faces: [Face; 6],
}

/// A ray's first hit: distance along the (unit) ray and the radiance it carries back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance from the ray origin, metres.
    pub distance: f32,
    /// Reflected radiance under unit illumination.
    pub radiance: f32,
}

/// Textures, the room (seen from inside) and the boxes in it.
#[derive(Clone, Debug)]
pub struct Scene {
    /// Every texture the surfaces refer to.
    pub textures: Vec<Texture>,
    /// The enclosing room; rays that miss every box end on its inside.
    pub room: SceneBox,
    /// Solid boxes inside the room.
    pub boxes: Vec<SceneBox>,
    /// Boxes grouped by contact, with each group's bounding box: a ray that misses a group's
    /// bounds (or reaches them beyond the nearest hit so far) skips all its boxes.
    groups: Vec<Group>,
}

#[derive(Clone, Debug)]
struct Group {
    min: [f32; 3],
    max: [f32; 3],
    members: Vec<usize>,
}

/// Entry and exit distances of a ray through an axis-aligned box, and the entry axis.
#[inline]
fn slab(min: &[f32; 3], max: &[f32; 3], origin: &[f32; 3], inv: &[f32; 3]) -> (f32, f32, usize) {
    let mut near = f32::NEG_INFINITY;
    let mut far = f32::INFINITY;
    let mut near_axis = 0;
    for a in 0..3 {
        let t1 = (min[a] - origin[a]) * inv[a];
        let t2 = (max[a] - origin[a]) * inv[a];
        let (lo, hi) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
        if lo > near {
            near = lo;
            near_axis = a;
        }
        far = far.min(hi);
    }
    (near, far, near_axis)
}

/// Connected components of boxes that touch or overlap (within 1 cm).
fn group_boxes(boxes: &[SceneBox]) -> Vec<Group> {
    let touch = |a: &SceneBox, b: &SceneBox| {
        (0..3).all(|k| a.min[k] <= b.max[k] + 0.01 && b.min[k] <= a.max[k] + 0.01)
    };
    let mut label: Vec<usize> = (0..boxes.len()).collect();
    // Union by repeated relabelling: a few dozen boxes, so quadratic passes are fine.
    loop {
        let mut changed = false;
        for i in 0..boxes.len() {
            for j in 0..boxes.len() {
                if label[j] > label[i] && touch(&boxes[i], &boxes[j]) {
                    label[j] = label[i];
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
    let mut groups: Vec<Group> = Vec::new();
    for (i, b) in boxes.iter().enumerate() {
        match groups.iter_mut().find(|g| label[g.members[0]] == label[i]) {
            Some(g) => {
                g.members.push(i);
                for k in 0..3 {
                    g.min[k] = g.min[k].min(b.min[k]);
                    g.max[k] = g.max[k].max(b.max[k]);
                }
            }
            None => groups.push(Group {
                min: b.min,
                max: b.max,
                members: vec![i],
            }),
        }
    }
    groups
}

/// Where the camera may go, and what it looks at, for trajectories fitted into a scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraRegion {
    /// Lower corner of the free space reserved for the camera, metres.
    pub min: Vector3<f64>,
    /// Upper corner, metres.
    pub max: Vector3<f64>,
    /// The point cameras look at (the middle of the desk).
    pub target: Vector3<f64>,
}

impl Scene {
    /// A scene from its textures, room and boxes; checks it with [`Scene::validate`].
    pub fn new(textures: Vec<Texture>, room: SceneBox, boxes: Vec<SceneBox>) -> Result<Self> {
        let groups = group_boxes(&boxes);
        let scene = Self {
            textures,
            room,
            boxes,
            groups,
        };
        scene.validate()?;
        Ok(scene)
    }

    /// Checks that every surface refers to an existing texture and that boxes are not empty.
    pub fn validate(&self) -> Result<()> {
        let n = self.textures.len();
        for (i, b) in std::iter::once(&self.room).chain(&self.boxes).enumerate() {
            if (0..3).any(|a| b.min[a].partial_cmp(&b.max[a]) != Some(std::cmp::Ordering::Less)) {
                return Err(Error::invalid(
                    format!("scene box {i}"),
                    "min < max on every axis",
                    format!("{:?}..{:?}", b.min, b.max),
                ));
            }
            let textures = b.faces.iter().flat_map(|f| {
                std::iter::once(f.surface.texture).chain(f.decals.iter().map(|d| d.surface.texture))
            });
            for t in textures {
                if t >= n {
                    return Err(Error::invalid(
                        format!("scene box {i} texture"),
                        format!("an index below {n}"),
                        t,
                    ));
                }
            }
        }
        Ok(())
    }

    /// The nearest hit of the ray `origin + s·dir` (`dir` a unit vector), with the pixel's
    /// angular size `pixel_angle` (radians) choosing the texture's mip level. `None` only when
    /// the origin lies outside the room.
    #[inline]
    pub fn trace(&self, origin: [f32; 3], dir: [f32; 3], pixel_angle: f32) -> Option<Hit> {
        let inv = [1.0 / dir[0], 1.0 / dir[1], 1.0 / dir[2]];
        // Room: the ray leaves through the face whose slab it crosses first.
        let mut best = f32::INFINITY;
        let mut hit: Option<(&SceneBox, usize)> = None;
        for a in 0..3 {
            let side = usize::from(dir[a] > 0.0);
            let plane = if side == 1 {
                self.room.max[a]
            } else {
                self.room.min[a]
            };
            let s = (plane - origin[a]) * inv[a];
            if s > 0.0 && s < best {
                best = s;
                hit = Some((&self.room, 2 * a + side));
            }
        }
        for group in &self.groups {
            if group.members.len() > 1 {
                let (near, far, _) = slab(&group.min, &group.max, &origin, &inv);
                if near > far || far <= 0.0 || near >= best {
                    continue;
                }
            }
            for &i in &group.members {
                let b = &self.boxes[i];
                let (near, far, axis) = slab(&b.min, &b.max, &origin, &inv);
                if near <= far && near > 0.0 && near < best {
                    best = near;
                    // Entering along +axis means through the min face.
                    hit = Some((b, 2 * axis + usize::from(dir[axis] < 0.0)));
                }
            }
        }
        let (b, face_index) = hit?;
        let p = [
            origin[0] + best * dir[0],
            origin[1] + best * dir[1],
            origin[2] + best * dir[2],
        ];
        let (u, v) = face_coordinates(b, face_index, p, std::ptr::eq(b, &self.room));
        let cos = dir[face_index / 2].abs().max(0.05);
        let footprint_m = best * pixel_angle / cos;
        let face = &b.faces[face_index];
        let mut surface = face.surface;
        let (mut s, mut t) = (u / surface.tile_m[0], v / surface.tile_m[1]);
        for decal in &face.decals {
            let [u0, v0, u1, v1] = decal.rect;
            if u >= u0 && u < u1 && v >= v0 && v < v1 {
                surface = Surface {
                    tile_m: [u1 - u0, v1 - v0],
                    wrap: Wrap::Clamp,
                    ..decal.surface
                };
                s = (u - u0) / (u1 - u0);
                t = (v - v0) / (v1 - v0);
                break;
            }
        }
        let texture = &self.textures[surface.texture];
        let footprint_texels = footprint_m * texture.width() as f32 / surface.tile_m[0];
        Some(Hit {
            distance: best,
            radiance: surface.gain * texture.sample(s, t, footprint_texels, surface.wrap),
        })
    }

    /// The desk scene: a 5 m × 4.5 m × 2.6 m room, a desk with objects on it, furniture, and
    /// `photos` (any number, reused round-robin; procedural textures stand in when empty) on
    /// the walls and the objects. Procedural textures are generated from `seed`.
    pub fn desk_room(photos: Vec<Texture>, seed: u64) -> Self {
        let mut textures = photos;
        let n_photos = textures.len();
        let add = |t: Texture, textures: &mut Vec<Texture>| {
            textures.push(t);
            textures.len() - 1
        };
        let floor = add(Texture::tiles(512, 8, (0.25, 0.6), seed), &mut textures);
        let wall = add(
            Texture::value_noise(256, 8, 5, 0.55, (0.45, 0.75), seed + 1),
            &mut textures,
        );
        let ceiling = add(Texture::tiles(256, 4, (0.6, 0.8), seed + 2), &mut textures);
        let wood = add(
            Texture::value_noise(512, 4, 6, 0.6, (0.3, 0.6), seed + 3),
            &mut textures,
        );
        let speckle = add(
            Texture::value_noise(256, 16, 4, 0.6, (0.15, 0.85), seed + 4),
            &mut textures,
        );
        let mut next_photo = 0usize;
        let mut photo = |gain: f32| {
            let texture = if n_photos == 0 {
                speckle
            } else {
                next_photo += 1;
                (next_photo - 1) % n_photos
            };
            Surface {
                texture,
                tile_m: [1.0, 1.0],
                wrap: Wrap::Clamp,
                gain,
            }
        };
        let tiled = |texture: usize, tile: f32, gain: f32| Surface {
            texture,
            tile_m: [tile, tile],
            wrap: Wrap::Repeat,
            gain,
        };

        let decal = |rect: [f32; 4], surface: Surface| Decal { rect, surface };
        // Room faces: x walls, y walls, floor, ceiling (face-coordinate metres from the corner).
        let mut room = SceneBox {
            min: [-2.5, -2.0, 0.0],
            max: [2.5, 2.5, 2.6],
            faces: std::array::from_fn(|i| Face {
                surface: match i {
                    4 => tiled(floor, 2.0, 1.0),
                    5 => tiled(ceiling, 1.5, 0.9),
                    _ => tiled(wall, 1.2, 0.95),
                },
                decals: Vec::new(),
            }),
        };
        // Far wall (y = 2.5), facing the desk: three pictures.
        room.faces[3].decals = vec![
            decal([0.6, 0.5, 1.8, 1.4], photo(1.0)),
            decal([2.0, 0.4, 3.0, 1.2], photo(0.9)),
            decal([3.3, 0.6, 4.4, 1.5], photo(1.0)),
        ];
        // Side walls and the wall behind the start position.
        room.faces[0].decals = vec![decal([1.2, 0.5, 2.4, 1.5], photo(0.9))];
        room.faces[1].decals = vec![decal([1.5, 0.6, 2.7, 1.4], photo(0.95))];
        room.faces[2].decals = vec![decal([1.8, 0.5, 3.0, 1.3], photo(0.9))];

        let plain = |surface: Surface| -> [Face; 6] {
            std::array::from_fn(|i| Face {
                surface: Surface {
                    // Faces differ in brightness like a diffusely lit object would.
                    gain: surface.gain * [0.75, 0.85, 0.8, 0.7, 0.6, 1.0][i],
                    ..surface
                },
                decals: Vec::new(),
            })
        };
        let mut boxes = Vec::new();
        // Desk top and legs.
        boxes.push(SceneBox {
            min: [-0.8, 0.9, 0.72],
            max: [0.8, 1.7, 0.76],
            faces: plain(tiled(wood, 0.8, 1.0)),
        });
        for (x, y) in [(-0.75, 0.95), (0.7, 0.95), (-0.75, 1.6), (0.7, 1.6)] {
            boxes.push(SceneBox {
                min: [x, y, 0.0],
                max: [x + 0.05, y + 0.05, 0.72],
                faces: plain(tiled(speckle, 0.3, 0.5)),
            });
        }
        // Objects on the desk, each with photographs on the faces towards the camera side.
        let mut object = |min: [f32; 3], max: [f32; 3], base: usize| {
            let mut faces = plain(tiled(base, 0.25, 0.9));
            let w = max[0] - min[0];
            let h = max[2] - min[2];
            let d = max[1] - min[1];
            // Front (y min) face: u runs along +x, v down from the top.
            faces[2].decals = vec![decal([0.1 * w, 0.1 * h, 0.9 * w, 0.9 * h], photo(0.95))];
            // Top face: u = x, v = y from the corner.
            faces[5].decals = vec![decal([0.05 * w, 0.05 * d, 0.95 * w, 0.95 * d], photo(1.0))];
            SceneBox { min, max, faces }
        };
        boxes.push(object([-0.6, 1.1, 0.76], [-0.3, 1.35, 1.0], speckle));
        boxes.push(object([0.05, 1.2, 0.76], [0.2, 1.5, 1.1], wood));
        boxes.push(object([0.35, 1.0, 0.76], [0.7, 1.3, 0.9], speckle));
        boxes.push(object([-0.25, 1.52, 0.76], [0.3, 1.6, 1.25], wall));
        // A cabinet right of the desk and a crate on the floor to the left.
        boxes.push(object([1.0, 1.2, 0.0], [1.6, 1.9, 0.9], wood));
        boxes.push(object([-1.8, 0.5, 0.0], [-1.2, 1.0, 0.5], speckle));
        let groups = group_boxes(&boxes);
        Self {
            textures,
            room,
            boxes,
            groups,
        }
    }

    /// The free space and look-at target of [`Scene::desk_room`]: at least 0.4 m from every
    /// wall, above the desk top, in front of the desk.
    pub fn desk_room_region() -> CameraRegion {
        CameraRegion {
            min: Vector3::new(-1.4, -1.4, 0.95),
            max: Vector3::new(1.4, 0.6, 1.8),
            target: Vector3::new(0.0, 1.3, 0.9),
        }
    }
}

/// Face coordinates (metres) of a point on face `face_index` of a box. Room faces are seen
/// from inside (the viewer-facing normal points into the box), box faces from outside.
#[inline]
fn face_coordinates(b: &SceneBox, face_index: usize, p: [f32; 3], inside: bool) -> (f32, f32) {
    let axis = face_index / 2;
    let side = face_index % 2;
    if axis == 2 {
        return (p[0] - b.min[0], p[1] - b.min[1]);
    }
    // Normal towards the viewer: ±axis. u = z × n is horizontal and points right.
    let outward_positive = side == 1;
    let n_positive = outward_positive != inside;
    let other = 1 - axis;
    // z × e_x = e_y, z × e_y = −e_x: u runs along +other when (axis = x, n = +x) or
    // (axis = y, n = −y).
    let u_positive = (axis == 0) == n_positive;
    let u = if u_positive {
        p[other] - b.min[other]
    } else {
        b.max[other] - p[other]
    };
    (u, b.max[2] - p[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn desk_room_is_valid_and_every_ray_from_the_region_hits() {
        let scene = Scene::desk_room(Vec::new(), 1);
        scene.validate().unwrap();
        let region = Scene::desk_room_region();
        let c = (region.min + region.max) / 2.0;
        let o = [c.x as f32, c.y as f32, c.z as f32];
        for k in 0..200 {
            let a = k as f32 * 0.7;
            let b = (k as f32 * 0.31).sin();
            let d = Vector3::new(
                a.cos() * (1.0 - b * b).sqrt(),
                a.sin() * (1.0 - b * b).sqrt(),
                b,
            );
            let hit = scene.trace(o, [d.x, d.y, d.z], 1e-3).unwrap();
            assert!(hit.distance > 0.3 && hit.distance < 7.0, "{hit:?}");
            assert!((0.0..=1.0).contains(&hit.radiance));
        }
    }

    #[test]
    fn boxes_are_grouped_by_contact() {
        let scene = Scene::desk_room(Vec::new(), 1);
        let sizes: Vec<usize> = scene.groups.iter().map(|g| g.members.len()).collect();
        // Desk top, four legs and four objects; the cabinet; the crate.
        assert_eq!(sizes, vec![9, 1, 1]);
    }

    #[test]
    fn nearest_box_face_wins() {
        let scene = Scene::desk_room(Vec::new(), 1);
        // Straight down from above the desk top: hits the top at z = 0.76 (or an object on it).
        let hit = scene
            .trace([0.0, 1.0, 1.5], [0.0, 0.0, -1.0], 1e-3)
            .unwrap();
        assert!((hit.distance - (1.5 - 0.76)).abs() < 1e-5, "{hit:?}");
        // Straight up: the ceiling at 2.6.
        let hit = scene.trace([0.0, 1.0, 1.5], [0.0, 0.0, 1.0], 1e-3).unwrap();
        assert!((hit.distance - 1.1).abs() < 1e-5, "{hit:?}");
    }
}
