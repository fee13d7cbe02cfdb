//! glTF 2.0 meshes from a reconstruction. UNDER CONSTRUCTION by the mesh helper.
