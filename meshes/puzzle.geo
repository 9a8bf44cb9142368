// Puzzle scene for demos/puzzle_initial_velocity.py (2D): a puzzle piece above a wavy ground.
// The piece is an s x s square with round tabs on its right and top sides and round blanks
// (holes) in its left and bottom sides, centred at (px, py) and turned by `turn` degrees. The
// ground's top is the polyline y = -amp cos(2 pi x / wave) through points `dx` apart.
// Physical groups: surfaces "ground" (cell tag 1), "piece" (2); curve "ground_top" (facet
// tag 1). Override the constants with -setnumber (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  x0 = {-0.3, Name "Parameters/x0"},        // ground from x0 to x1, bottom at -depth
  x1 = {1.9, Name "Parameters/x1"},
  depth = {0.15, Name "Parameters/depth"},
  amp = {0.03, Name "Parameters/amp"},      // wave amplitude and length
  wave = {0.4, Name "Parameters/wave"},
  dx = {0.05, Name "Parameters/dx"},        // spacing of the ground's top vertices
  s = {0.16, Name "Parameters/s"},          // side of the piece and radius of its tabs/blanks
  rt = {0.035, Name "Parameters/rt"},
  px = {0.1, Name "Parameters/px"},         // centre and rotation of the piece
  py = {0.3, Name "Parameters/py"},
  turn = {10, Name "Parameters/turn"},
  h = {0.02, Name "Parameters/h"},          // mesh size of the piece
  hg = {10, Name "Parameters/hg"}           // mesh size inside the ground
];

// The ground is a static obstacle (all its nodes are held): its only vertices are the points
// of the wave and its two bottom corners (more vertices on the surface would add forces that
// jitter whenever a vertex of the piece passes one).
n = Floor((x1 - x0) / dx + 0.5);
For k In {0 : n}
  xk = x0 + k * (x1 - x0) / n;
  Point(100 + k) = {xk, -amp * Cos(2 * Pi * xk / wave), 0, hg};
EndFor
Point(1) = {x1, -depth, 0, hg};
Point(2) = {x0, -depth, 0, hg};
For k In {0 : n - 1}
  Line(100 + k) = {100 + k, 101 + k};
EndFor
Line(1) = {100 + n, 1};
Line(2) = {1, 2};
Line(3) = {2, 100};
Curve Loop(1) = {100 : 100 + n - 1, 1, 2, 3};
Plane Surface(1) = {1};

c = 0.6 * rt;  // tab/blank centres lie this far outside/inside the sides
Rectangle(10) = {-s / 2, -s / 2, 0, s, s};
Disk(11) = {s / 2 + c, 0, 0, rt, rt};
Disk(12) = {0, s / 2 + c, 0, rt, rt};
Disk(13) = {-s / 2 + c, 0, 0, rt, rt};
Disk(14) = {0, -s / 2 + c, 0, rt, rt};
tabbed[] = BooleanUnion{ Surface{10}; Delete; }{ Surface{11, 12}; Delete; };
piece[] = BooleanDifference{ Surface{tabbed[]}; Delete; }{ Surface{13, 14}; Delete; };
Rotate {{0, 0, 1}, {0, 0, 0}, turn * Pi / 180} { Surface{piece[]}; }
Translate {px, py, 0} { Surface{piece[]}; }

Physical Surface("ground", 1) = {1};
Physical Surface("piece", 2) = {piece[]};
Physical Curve("ground_top", 1) = {100 : 100 + n - 1};

MeshSize{PointsOf{Surface{piece[]};}} = h;
Mesh.CharacteristicLengthMax = hg;
Mesh.CharacteristicLengthMin = 0;
