"""Exit 0 when SAPIEN can render an image on this machine, 1 otherwise (used by the set-up script)."""

from __future__ import annotations

import sys


def probe() -> bool:
    """Render one 32×24 frame of an empty scene; True when SAPIEN found a rendering device."""
    try:
        import sapien

        sapien.render.set_camera_shader_dir("trivial")
        scene = sapien.Scene()
        entity = sapien.Entity()
        camera = sapien.render.RenderCameraComponent(32, 24)
        entity.add_component(camera)
        scene.add_entity(entity)
        scene.update_render()
        camera.take_picture()
        camera.get_picture("Color")
    except Exception as exc:  # any failure means "cannot render here"
        print(f"SAPIEN cannot render: {exc}", file=sys.stderr)
        return False
    return True


if __name__ == "__main__":
    sys.exit(0 if probe() else 1)
