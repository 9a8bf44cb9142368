// 2D bridge for demos/bridge_fabricated.py and demos/bridge_stress.py: a deck of span L and
// height H clamped at both ends (x = 0 and x = L), with a lower beam and an upper chord joined
// by verticals around NH openings with rounded corners (a Vierendeel truss).
// Physical groups: surface "bridge" (cell tag 1); curves "fixed_left" (x = 0, facet tag 1),
// "fixed_right" (x = L, 2) and the three loaded segments of the lower beam's underside
// "load_1", "load_2", "load_3" (facet tags 3, 4, 5; width LW, centred under the three
// openings). Override the constants with -setnumber (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  L = {10.0, Name "Parameters/L"},    // span
  H = {2.0, Name "Parameters/H"},     // height
  TB = {0.3, Name "Parameters/TB"},   // lower beam thickness
  TT = {0.35, Name "Parameters/TT"},  // upper chord thickness
  A = {1.2, Name "Parameters/A"},     // solid end blocks
  WV = {0.35, Name "Parameters/WV"},  // verticals between openings
  R = {0.12, Name "Parameters/R"},    // corner radius of the openings
  LW = {1.0, Name "Parameters/LW"},   // width of each loaded segment
  h = {0.1, Name "Parameters/h"}      // mesh size
];

NH = 3;
W = (L - 2 * A - (NH - 1) * WV) / NH;  // width of an opening
Rectangle(1) = {0, 0, 0, L, H};
For k In {0 : NH - 1}
  Rectangle(10 + k) = {A + k * (W + WV), TB, 0, W, H - TB - TT, R};
EndFor
body[] = BooleanDifference{ Surface{1}; Delete; }{ Surface{10 : 10 + NH - 1}; Delete; };

// split the underside at the ends of the loaded segments
For k In {0 : NH - 1}
  xc = A + k * (W + WV) + W / 2;
  p0 = newp; Point(p0) = {xc - LW / 2, 0, 0};
  p1 = newp; Point(p1) = {xc + LW / 2, 0, 0};
  seg[k] = newl; Line(seg[k]) = {p0, p1};
EndFor
parts[] = BooleanFragments{ Surface{body[]}; Delete; }{ Curve{seg[]}; Delete; };

eps = 1e-6 * L;
left[] = Curve In BoundingBox{-eps, -eps, -eps, eps, H + eps, eps};
right[] = Curve In BoundingBox{L - eps, -eps, -eps, L + eps, H + eps, eps};
Physical Surface("bridge", 1) = {Surface{:}};
Physical Curve("fixed_left", 1) = {left[]};
Physical Curve("fixed_right", 2) = {right[]};
For k In {0 : NH - 1}
  xc = A + k * (W + WV) + W / 2;
  load[] = Curve In BoundingBox{xc - LW / 2 - eps, -eps, -eps, xc + LW / 2 + eps, eps, eps};
  Physical Curve(Sprintf("load_%g", k + 1), 3 + k) = {load[]};
EndFor

Mesh.CharacteristicLengthMax = h;
Mesh.CharacteristicLengthMin = 0;
