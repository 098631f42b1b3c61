"""Stage 5, retarget: from key weights to a character's targets.

* :class:`Mapping` and :func:`retarget` — key → target gains, by name or from ``MAP.json``, and
  :func:`drive_gaze` — its gaze targets following the tracker's gaze scores;
* :func:`auto_targets`, :func:`propose_targets`, :func:`propose_mapping` — no sculpting: the
  character's version of every key shape (expression transfer), or a key → blendshape mapping
  for a rig with shapes of its own;
* :func:`score_floor`, :func:`with_floor` — the peer's path as the floor: an ARKit rig's targets
  following the tracker's own scores less the character's rest reading, unless the evidence says better;
* :func:`refine_mapping` — render and compare: the mapping's targets the tracker's scores barely
  see (jaw, lower lip, squint ...) refined on the landmarks of the character's own renders;
* :func:`transfer_expressions` — the transfer itself (deformation transfer on the mesh);
* :class:`Correspondence`, :func:`find_correspondence`, :func:`read_correspondence` — where the
  landmarks sit on the character (given in a file, or found on a render);
* :func:`stylised_head`, :func:`default_character` — keyshape's built-in character, and
  :func:`with_gaze_targets` / :func:`gaze_weights` — its eyes turned by the gaze;
* :func:`complete_mirrors` — mirrored keys' targets made from their sources' on a symmetric mesh.
"""

from ._character import GAZE_NAMES, Character, canonical_face, gaze_weights, stylised_head, with_gaze_targets
from ._correspond import Correspondence, correspondence_from_dict, read_correspondence
from ._correspond_auto import NoFaceFound, find_correspondence
from ._floor import KEY_TARGETS, key_targets, score_floor, with_floor
from ._mapping import Mapping, drive_gaze, retarget
from ._mirrored import complete_mirrors, mirror_sources
from ._propose import (
    GAZE_TARGETS,
    AutoTargets,
    KeyScores,
    auto_targets,
    default_character,
    gaze_channels,
    no_face_on,
    propose_mapping,
    propose_targets,
    proposer,
    resolve_correspondence,
)
from ._refine import REFINED_SCORES, Refinement, refinable_targets, refine_mapping
from ._transfer import LandmarkMotion, feature_groups, landmark_motion, spread, transfer_expressions

__all__ = ["Mapping", "retarget", "drive_gaze", "complete_mirrors", "mirror_sources",
           "AutoTargets", "KeyScores", "auto_targets", "gaze_channels", "propose_targets", "propose_mapping",
           "proposer",
           "resolve_correspondence",
           "refine_mapping", "refinable_targets", "Refinement", "REFINED_SCORES",
           "score_floor", "with_floor", "key_targets", "KEY_TARGETS", "GAZE_TARGETS",
           "LandmarkMotion", "landmark_motion", "transfer_expressions", "feature_groups", "spread",
           "Correspondence", "find_correspondence", "read_correspondence", "correspondence_from_dict",
           "NoFaceFound", "no_face_on",
           "Character", "stylised_head", "canonical_face", "default_character", "with_gaze_targets",
           "gaze_weights", "GAZE_NAMES"]
