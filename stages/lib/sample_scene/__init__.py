"""The embedded sample's own renderer and scene generators (independent of the splat code).

textures: procedural textures; meshes: textured primitives; objects: the object classes; rooms:
furnished rooms and lighting; raytrace: Open3D ray casting + Blinn-Phong shading; cameras: K and
poses; photo: exposure and camera-B effects; capture / backgrounds / testsets: the three kinds of
pictures; videos and contact: output helpers.
"""
