//! The glTF 2.0 document of a mesh: its JSON (buffers, views, accessors with their bounds,
//! the textured material) and its binary buffer.

use gltf_json as json;
use json::accessor::{ComponentType, GenericComponentType, Type};
use json::buffer::Target;
use json::validation::{Checked::Valid, USize64};
use serde_json::Value;

use super::error::MeshError;
use super::texture::albedo_png;
use super::triangulate::triangulate_with;
use crate::core::camera::Pinhole;
use crate::core::options::MeshOptions;
use crate::core::reconstruction::Reconstruction;

/// The glTF document and its binary buffer (views 4-byte aligned, length padded to 4).
pub(super) fn document(
    rec: &Reconstruction,
    opts: &MeshOptions,
    camera: Option<&Pinhole>,
) -> Result<(json::Root, Vec<u8>), MeshError> {
    let (mesh, texture) = rayon::join(|| triangulate_with(rec, opts, camera), || albedo_png(rec));
    let (mesh, texture) = (mesh?, texture?);
    let mut root = json::Root {
        asset: json::Asset {
            generator: Some(format!("photostereo {}", env!("CARGO_PKG_VERSION"))),
            ..Default::default()
        },
        ..Default::default()
    };
    let buffer = root.push(json::Buffer {
        byte_length: USize64(0), // set below, once the buffer is complete
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    // Sized up front (positions, normals, uvs, u32 indices at most, texture, padding): a
    // growing buffer of ~10 MB was copied by each reallocation.
    let (n, t) = (mesh.positions.len(), mesh.triangles.len());
    let mut bin = Vec::with_capacity(n * (12 + 12 + 8) + t * 12 + texture.len() + 5 * 3);
    let mut view = |root: &mut json::Root, bytes: &[u8], target: Option<Target>| {
        bin.resize(bin.len().next_multiple_of(4), 0);
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        root.push(json::buffer::View {
            buffer,
            byte_length: bytes.len().into(),
            byte_offset: Some(offset.into()),
            byte_stride: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        })
    };
    let floats = |v: &[f32]| {
        let mut out = Vec::with_capacity(v.len() * 4);
        v.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
        out
    };

    let (lo, hi) = bounds(&mesh.positions);
    let v = view(
        &mut root,
        &floats(mesh.positions.as_flattened()),
        Some(Target::ArrayBuffer),
    );
    let positions = accessor(
        &mut root,
        v,
        n,
        ComponentType::F32,
        Type::Vec3,
        Some((lo, hi)),
    );
    let v = view(
        &mut root,
        &floats(mesh.normals.as_flattened()),
        Some(Target::ArrayBuffer),
    );
    let normals = accessor(&mut root, v, n, ComponentType::F32, Type::Vec3, None);
    let v = view(
        &mut root,
        &floats(mesh.uvs.as_flattened()),
        Some(Target::ArrayBuffer),
    );
    let uvs = accessor(&mut root, v, n, ComponentType::F32, Type::Vec2, None);
    // u16 when every index fits below 65535 (that value means primitive restart).
    let flat = mesh.triangles.as_flattened();
    let (bytes, kind): (Vec<u8>, _) = if n < usize::from(u16::MAX) {
        let b = flat.iter().flat_map(|&i| (i as u16).to_le_bytes());
        (b.collect(), ComponentType::U16)
    } else {
        (
            flat.iter().flat_map(|i| i.to_le_bytes()).collect(),
            ComponentType::U32,
        )
    };
    let v = view(&mut root, &bytes, Some(Target::ElementArrayBuffer));
    let indices = accessor(&mut root, v, flat.len(), kind, Type::Scalar, None);
    let image_view = view(&mut root, &texture, None);
    bin.resize(bin.len().next_multiple_of(4), 0);
    root.buffers[0].byte_length = bin.len().into();

    let image = root.push(json::Image {
        buffer_view: Some(image_view),
        mime_type: Some(json::image::MimeType("image/png".into())),
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    let sampler = root.push(json::texture::Sampler {
        mag_filter: Some(Valid(json::texture::MagFilter::Linear)),
        min_filter: Some(Valid(json::texture::MinFilter::LinearMipmapLinear)),
        wrap_s: Valid(json::texture::WrappingMode::ClampToEdge),
        wrap_t: Valid(json::texture::WrappingMode::ClampToEdge),
        ..Default::default()
    });
    let texture = root.push(json::Texture {
        sampler: Some(sampler),
        source: image,
        extensions: None,
        extras: Default::default(),
    });
    // A matte, non-metallic surface: what photometric stereo assumes (Lambertian).
    let material = root.push(json::Material {
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_texture: Some(json::texture::Info {
                index: texture,
                tex_coord: 0,
                extensions: None,
                extras: Default::default(),
            }),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(1.0),
            ..Default::default()
        },
        double_sided: false,
        ..Default::default()
    });
    let attributes = [
        (json::mesh::Semantic::Positions, positions),
        (json::mesh::Semantic::Normals, normals),
        (json::mesh::Semantic::TexCoords(0), uvs),
    ];
    let primitive = json::mesh::Primitive {
        attributes: attributes.into_iter().map(|(k, a)| (Valid(k), a)).collect(),
        extensions: None,
        extras: Default::default(),
        indices: Some(indices),
        material: Some(material),
        mode: Valid(json::mesh::Mode::Triangles),
        targets: None,
    };
    let mesh = root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        primitives: vec![primitive],
        weights: None,
    });
    let node = root.push(json::Node {
        mesh: Some(mesh),
        ..Default::default()
    });
    let scene = root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        nodes: vec![node],
    });
    root.scene = Some(scene);
    Ok((root, bin))
}

fn accessor(
    root: &mut json::Root,
    view: json::Index<json::buffer::View>,
    count: usize,
    component: ComponentType,
    kind: Type,
    bounds: Option<(Value, Value)>,
) -> json::Index<json::Accessor> {
    let (min, max) = bounds.unzip();
    root.push(json::Accessor {
        buffer_view: Some(view),
        byte_offset: None,
        count: count.into(),
        component_type: Valid(GenericComponentType(component)),
        extensions: None,
        extras: Default::default(),
        type_: Valid(kind),
        min,
        max,
        normalized: false,
        sparse: None,
    })
}

/// Per-axis minimum and maximum as JSON arrays (f32 → f64 is exact, so they match the
/// data bit for bit as the spec requires).
fn bounds(points: &[[f32; 3]]) -> (Value, Value) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (Value::from(lo.to_vec()), Value::from(hi.to_vec()))
}
