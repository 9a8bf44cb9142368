// Two interlocking 2D parts for demos/interlocking.py (after Tozoni et al. 2021): a bottom
// plate [0, LX] x [0, HB] with a dovetail socket cut into the middle of its top, and a top
// plate [0, LX] x [HB + G, HB + G + HT] whose dovetail tenon sits in the socket. The tenon is
// the socket shrunk by the gap G everywhere (the parts never touch: the IPC barrier acts
// across gaps below its activation distance). Socket: half-width AT at the plate surface,
// AB at its bottom, depth D.
// Physical groups: surfaces "bottom" (cell tag 1) and "top" (2); curves "fixed" (the underside
// of the bottom plate, facet tag 1) and "load" (the top side of the top plate, 2). Override the
// constants with -setnumber (diffsolids.mesh.from_geo's `numbers`).
DefineConstant[
  LX = {4.0, Name "Parameters/LX"},   // width of both plates
  HB = {1.0, Name "Parameters/HB"},   // bottom plate height
  HT = {0.8, Name "Parameters/HT"},   // top plate height (above the gap)
  D = {0.5, Name "Parameters/D"},     // socket depth
  AT = {0.3, Name "Parameters/AT"},   // socket half-width at the surface
  AB = {0.5, Name "Parameters/AB"},   // socket half-width at its bottom
  G = {0.01, Name "Parameters/G"},    // gap between the parts
  h = {0.08, Name "Parameters/h"}     // mesh size
];

XC = LX / 2;
LW = Sqrt((AB - AT)^2 + D^2);          // length of a socket wall
// x of the tenon's left wall (the socket's left wall moved by G along its normal) at the
// heights of the top plate's underside (HB + G) and of the tenon's end (HB - D + G)
x_top = XC - AB + (D + G) * (AB - AT) / D + G * LW / D;
x_bot = XC - AB + G * (AB - AT) / D + G * LW / D;

// bottom plate with the socket
Point(1) = {0, 0, 0, h};
Point(2) = {LX, 0, 0, h};
Point(3) = {LX, HB, 0, h};
Point(4) = {XC + AT, HB, 0, h};
Point(5) = {XC + AB, HB - D, 0, h};
Point(6) = {XC - AB, HB - D, 0, h};
Point(7) = {XC - AT, HB, 0, h};
Point(8) = {0, HB, 0, h};
For k In {1 : 8}
  Line(k) = {k, k % 8 + 1};
EndFor
Curve Loop(1) = {1 : 8};
Plane Surface(1) = {1};

// top plate with the tenon
Point(11) = {0, HB + G, 0, h};
Point(12) = {x_top, HB + G, 0, h};
Point(13) = {x_bot, HB - D + G, 0, h};
Point(14) = {2 * XC - x_bot, HB - D + G, 0, h};
Point(15) = {2 * XC - x_top, HB + G, 0, h};
Point(16) = {LX, HB + G, 0, h};
Point(17) = {LX, HB + G + HT, 0, h};
Point(18) = {0, HB + G + HT, 0, h};
For k In {11 : 18}
  Line(k) = {k, (k - 10) % 8 + 11};
EndFor
Curve Loop(2) = {11 : 18};
Plane Surface(2) = {2};

Physical Surface("bottom", 1) = {1};
Physical Surface("top", 2) = {2};
Physical Curve("fixed", 1) = {1};
Physical Curve("load", 2) = {17};

Mesh.CharacteristicLengthMax = h;
Mesh.CharacteristicLengthMin = 0;
