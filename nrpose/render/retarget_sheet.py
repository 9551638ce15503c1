"""Contact sheet of a retargeted motion: the target character posed by linear blend skinning
of its meshes (numpy), with the source skeleton, scaled by the root-motion scale, drawn
beside it; every panel is centred horizontally on the hips."""
from __future__ import annotations

import numpy as np

from ..model.skeleton import LocalPose
from ..pose.skinning import lbs_reference
from .preview import spread
from .sheet import save_contact_sheet, view_matrix

__all__ = ["save_retarget_sheet"]


def _skinned_frames(character, G: np.ndarray):
    """Posed vertices (F, V, 3) of all meshes by linear blend skinning, and the faces."""
    mats = character.skin_matrices(G)
    verts, faces, offset = [], [], 0
    for mesh in character.meshes:
        if mesh.joints is None:
            continue
        verts.append(np.stack([lbs_reference(mesh.vertices, mesh.joints, mesh.weights, M) for M in mats]))
        faces.append(mesh.faces + offset)
        offset += len(mesh.vertices)
    if not verts:
        return None, None
    return np.concatenate(verts, axis=1), np.concatenate(faces)


def save_retarget_sheet(path, source, clip, target, times, local, plan, title: str = "",
                        max_panels: int = 8) -> list[int]:
    """Contact sheet: retargeted target (mesh, or bones without one) with the source skeleton beside it."""
    F = len(times)
    pick = np.arange(F) if F <= max_panels else spread(F, max_panels)
    Gt = target.skeleton.forward_kinematics(_take(local, pick))
    Gs = source.skeleton.forward_kinematics(clip.sample(times[pick]))
    hips_t = Gt[:, plan.root, :3, 3].copy()
    hips_s = Gs[:, plan.mapping[plan.root], :3, 3].copy()
    hips_t[:, 1] = 0.0
    hips_s[:, 1] = 0.0
    V, faces = _skinned_frames(target, Gt)
    tb = target.skeleton.bones()
    t_ends, _ = tb.pose(Gt)
    if V is None:
        V = t_ends.reshape(len(pick), -1, 3)
    V = V - hips_t[:, None]
    height = float(np.ptp(target.skeleton.rest_globals()[:, 1, 3])) or 1.0
    right = view_matrix()[0].copy()
    right[1] = 0.0
    right /= np.linalg.norm(right) or 1.0
    sb = source.skeleton.bones()
    s_ends, _ = sb.pose(Gs)
    s_ends = plan.scale * (s_ends - hips_s[:, None, None]) + 0.75 * height * right
    return save_contact_sheet(path, V, faces, times[pick], title=title, max_panels=max_panels,
                              handles_per_frame=list(s_ends))


def _take(local, index):
    return LocalPose(local.translation[index], local.rotation[index], local.scale[index])
