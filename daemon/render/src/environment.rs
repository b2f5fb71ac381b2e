//! Environments for image-based lighting (DESIGN.md "IBL"), world up = +z. Every environment is
//! held as an equirectangular float RGB image: direction d maps to u = atan2(d.y, d.x) / (2 pi)
//! mod 1 (column 0 looks along +x, columns advance counter-clockwise seen from above),
//! v = acos(d.z) / pi (row 0 is the zenith). Placeholder: being written.
