// Sliding scene for demos/sliding_friction.py (2D): a rounded block on a ramp. The ramp is the
// right triangle (0, 0), (L, 0), (0, L tan(theta)); the block (w x h, corner radius r) rests on
// its hypotenuse a small gap above it, its lower-left corner s0 down the slope from the top.
// Physical groups: surfaces "ramp" (cell tag 1), "block" (2); curve "slope" (facet tag 1).
// Override the constants with -setnumber (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  theta = {30, Name "Parameters/theta"},   // slope angle [degrees]
  L = {2.0, Name "Parameters/L"},          // horizontal length of the ramp
  w = {0.2, Name "Parameters/w"},          // block width (along the slope) and height
  hb = {0.1, Name "Parameters/hb"},
  r = {0.02, Name "Parameters/r"},         // corner radius of the block
  s0 = {0.1, Name "Parameters/s0"},        // distance of the block from the top of the slope
  gap = {0.0005, Name "Parameters/gap"},   // initial gap between the block and the slope
  h = {0.025, Name "Parameters/h"},        // mesh size of the block
  hr = {10, Name "Parameters/hr"}          // mesh size of the ramp (see below)
];

t = theta * Pi / 180;
H = L * Tan(t);

// The ramp is a static obstacle (all its nodes are held): meshed as coarsely as possible, so
// that the slope is one straight edge (vertices on it would make the sliding forces jitter).
Point(1) = {0, 0, 0, hr};
Point(2) = {L, 0, 0, hr};
Point(3) = {0, H, 0, hr};
Line(1) = {1, 2};
Line(2) = {2, 3};
Line(3) = {3, 1};
Curve Loop(1) = {1, 2, 3};
Plane Surface(1) = {1};

Rectangle(2) = {0, gap, 0, w, hb, r};
Rotate {{0, 0, 1}, {0, 0, 0}, -t} { Surface{2}; }
Translate {s0 * Cos(t), H - s0 * Sin(t), 0} { Surface{2}; }

Physical Surface("ramp", 1) = {1};
Physical Surface("block", 2) = {2};
Physical Curve("slope", 1) = {2};

MeshSize{PointsOf{Surface{2};}} = h;
Mesh.CharacteristicLengthMax = hr;
Mesh.CharacteristicLengthMin = 0;
