// Test mesh (tests/test_mesh.py): two unit squares [0, 1] x [0, 1] and [1, 2] x [0, 1] sharing
// the edge x = 1 (conforming). Bodies "left_body" (cell tag 1) and "right_body" (2); boundary
// curves "clamp" (x = 0, facet tag 11), "load" (x = 2, 12) and "bottom" (y = 0, 13).
DefineConstant[ h = {0.5, Name "Parameters/h"} ];

Point(1) = {0, 0, 0, h};
Point(2) = {1, 0, 0, h};
Point(3) = {2, 0, 0, h};
Point(4) = {2, 1, 0, h};
Point(5) = {1, 1, 0, h};
Point(6) = {0, 1, 0, h};

Line(1) = {1, 2};
Line(2) = {2, 3};
Line(3) = {3, 4};
Line(4) = {4, 5};
Line(5) = {5, 6};
Line(6) = {6, 1};
Line(7) = {2, 5};

Curve Loop(1) = {1, 7, 5, 6};
Plane Surface(1) = {1};
Curve Loop(2) = {2, 3, 4, -7};
Plane Surface(2) = {2};

Physical Surface("left_body", 1) = {1};
Physical Surface("right_body", 2) = {2};
Physical Curve("clamp", 11) = {6};
Physical Curve("load", 12) = {3};
Physical Curve("bottom", 13) = {1, 2};
