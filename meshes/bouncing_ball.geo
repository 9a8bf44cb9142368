// Ball dropped on a plank, for demos/bouncing_ball_height.py: a disk (2D, D = 2) or a sphere
// (3D, D = 3) of radius R centred at height R + GAP above the plank, a plank of length PL and
// thickness PT whose top face is y = 0 (2D) or z = 0 (3D, plank width PW).
// Physical groups: "plank" (cell tag 1), "ball" (cell tag 2); "plank_ends" (facet tag 1: the
// plank's faces at x = -+PL/2). Override the constants with -setnumber
// (diffsolids.mesh.from_geo's `numbers`).
SetFactory("OpenCASCADE");

DefineConstant[
  D = {2, Name "Parameters/D"},        // dimension
  R = {0.1, Name "Parameters/R"},      // ball radius
  GAP = {0.03, Name "Parameters/GAP"}, // initial gap between ball and plank
  PL = {0.6, Name "Parameters/PL"},    // plank length
  PT = {0.04, Name "Parameters/PT"},   // plank thickness
  PW = {0.3, Name "Parameters/PW"},    // plank width (3D)
  h = {0.025, Name "Parameters/h"},    // mesh size of the ball
  hp = {0.04, Name "Parameters/hp"}    // mesh size of the plank
];

eps = 1e-6 * PL;
If (D == 2)
  Rectangle(1) = {-PL / 2, -PT, 0, PL, PT};
  Disk(2) = {0, R + GAP, 0, R, R};
  Physical Surface("plank", 1) = {1};
  Physical Surface("ball", 2) = {2};
  ends[] = Curve In BoundingBox{-PL / 2 - eps, -PT - eps, -eps, -PL / 2 + eps, eps, eps};
  ends[] += Curve In BoundingBox{PL / 2 - eps, -PT - eps, -eps, PL / 2 + eps, eps, eps};
  Physical Curve("plank_ends", 1) = {ends[]};
  MeshSize{ PointsOf{ Surface{1}; } } = hp;
  MeshSize{ PointsOf{ Surface{2}; } } = h;
Else
  Box(1) = {-PL / 2, -PW / 2, -PT, PL, PW, PT};
  Sphere(2) = {0, 0, R + GAP, R};
  Physical Volume("plank", 1) = {1};
  Physical Volume("ball", 2) = {2};
  ends[] = Surface In BoundingBox{-PL / 2 - eps, -PW / 2 - eps, -PT - eps, -PL / 2 + eps, PW / 2 + eps, eps};
  ends[] += Surface In BoundingBox{PL / 2 - eps, -PW / 2 - eps, -PT - eps, PL / 2 + eps, PW / 2 + eps, eps};
  Physical Surface("plank_ends", 1) = {ends[]};
  MeshSize{ PointsOf{ Volume{1}; } } = hp;
  MeshSize{ PointsOf{ Volume{2}; } } = h;
EndIf

Mesh.CharacteristicLengthMin = 0;
Mesh.CharacteristicLengthFromPoints = 1;
Mesh.MeshSizeExtendFromBoundary = 1;
