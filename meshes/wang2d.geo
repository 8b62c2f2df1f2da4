// Seed 000 2D bed (Wang et al. 2020), Table 2: 90 mm x 500 mm in 18 x 100 quadrilaterals (5 mm).
// Triangles instead: gmsh -2 wang2d.geo -setnumber quads 0
// Same geometry as febed.meshing.build_msh("wang2d"); tests/test_meshing.py checks they agree.
DefineConstant[ quads = 1 ];
Lx = 0.09; Ly = 0.5; nx = 18; ny = 100;
Point(1) = {0, 0, 0}; Point(2) = {Lx, 0, 0}; Point(3) = {Lx, Ly, 0}; Point(4) = {0, Ly, 0};
Line(1) = {1, 2}; Line(2) = {2, 3}; Line(3) = {3, 4}; Line(4) = {4, 1};
Transfinite Curve{1, 3} = nx + 1; Transfinite Curve{2, 4} = ny + 1;
Curve Loop(1) = {1, 2, 3, 4}; Plane Surface(1) = {1};
Transfinite Surface{1};
If (quads) Recombine Surface{1}; EndIf
Physical Curve("inlet") = {1};
Physical Curve("walls") = {2, 4};
Physical Curve("outlet") = {3};
Physical Surface("fluid") = {1};
