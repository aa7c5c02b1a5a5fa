"""Which image pairs to match: every pair, or neighbours in capture order plus loop pairs.

The pair lists are made here rather than by COLMAP's own pair generators for two
reasons: images are ordered by natural name order (``2.jpg`` before ``10.jpg``; COLMAP's
sequential matcher sorts names as text), and the loop pairs come from evenly spaced key
images matched with each other, which closes loops without a vocabulary tree (COLMAP's
loop detection needs one, and fetching it needs a network).
"""

from __future__ import annotations

# Up to this many images, `auto` matches every pair (exhaustive); beyond, sequential.
EXHAUSTIVE_MAX_IMAGES = 150
# Sequential matching: how many key images are matched with each other to close loops.
LOOP_KEY_IMAGES = 40


def exhaustive_pairs(n: int) -> list[tuple[int, int]]:
    """Every pair (i, j), i < j, of n images."""
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def sequential_pairs(n: int, overlap: int = 10, quadratic: bool = True, loop_key_images: int = LOOP_KEY_IMAGES) -> list[tuple[int, int]]:
    """Pairs for n images in capture order.

    - each image with the next `overlap` images;
    - with `quadratic`, also with the images 2^k ahead (k = 0 … overlap - 1), which ties
      together parts of a sweep seen again after a while (as COLMAP's quadratic overlap);
    - `loop_key_images` evenly spaced images matched with each other, so a path that
      comes back to its start is tied there too.
    """
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        for d in range(1, overlap + 1):
            if i + d < n:
                pairs.add((i, i + d))
        if quadratic:
            for k in range(overlap):
                d = 2**k
                if i + d >= n:
                    break
                pairs.add((i, i + d))
    if loop_key_images > 1 and n > 2:
        step = max(1, -(-n // loop_key_images))
        keys = list(range(0, n, step))
        for a in range(len(keys)):
            for b in range(a + 1, len(keys)):
                pairs.add((keys[a], keys[b]))
    return sorted(pairs)


def choose_matcher(matcher: str, n_images: int, kind: str) -> str:
    """`auto`: sequential for a video (frames in time order), exhaustive for up to
    EXHAUSTIVE_MAX_IMAGES photos, sequential (natural name order) beyond."""
    if matcher != "auto":
        return matcher
    if kind == "video":
        return "sequential"
    return "exhaustive" if n_images <= EXHAUSTIVE_MAX_IMAGES else "sequential"
