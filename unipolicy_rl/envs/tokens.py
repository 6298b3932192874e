"""The keys a robot of any morphology is observed and driven through: one token per link, padded.

Robots of different grammar derivations have different numbers of links and joints, so a batch
of them cannot share the flat ``observation`` / ``action`` of one topology. Instead each robot is
a sequence of link tokens padded to the largest robot the run may meet, with masks saying which
slots are real. These names are the contract between the env that writes them, the policies
that read them and the learners that must ignore the padding; they live here, once.

Shapes (``*`` is the env's batch shape, ``L`` the padded number of links):

- ``TOKENS``: ``[*, L, F]`` float32, one feature row per link (the root, the base link, first).
- ``TOKEN_MASK``: ``[*, L]`` bool, True for a real link, False for padding.
- ``TOKEN_PARENT``: ``[*, L]`` int64, the token index of the link's parent in the body tree;
  -1 for the root and for padding (what a graph-masked attention reads).
- ``ACTION_MASK``: ``[*, L]`` bool, True where the link's joint to its parent is actuated.
  The action is ``[*, L]``: slot ``i`` drives link ``i``'s parent joint; slots where the mask
  is False (the root, fixed joints, padding) are ignored by the env and must count for nothing
  in a learner's log-probabilities, entropy and KL.
"""

from __future__ import annotations

TOKENS = "tokens"
TOKEN_MASK = "token_mask"
TOKEN_PARENT = "token_parent"
ACTION_MASK = "action_mask"
