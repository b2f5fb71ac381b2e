// Shared include: what a pixel's colour says in w (written by Kernel::Isosurface, read by every
// kernel after it). w >= 0.5: the primary ray hit the surface; a hit drawn with level 0 where it
// lies (always, for a volume held whole) is 1, one drawn from a coarser level of a bricked volume
// (DESIGN.md "Large volumes") 0.75; no hit 0. The frame's counters count both kinds of hit.

const HIT_LEVEL0: f32 = 1.0;
const HIT_COARSER: f32 = 0.75;

fn is_hit(w: f32) -> bool {
    return w >= 0.5;
}

fn is_level0_hit(w: f32) -> bool {
    return w >= 0.875;
}
