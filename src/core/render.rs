//! Pictures drawn from a reconstruction: shading under a light, needle map, colour maps.
