// A cylindrical bed (diameter 50 mm, height 150 mm, axis z) in tetrahedra: any gmsh geometry with named
// physical groups is a febed mesh.  gmsh -3 cylinder.geo -setnumber h 0.004
// Same geometry as febed.meshing.build_msh("cylinder", size=h).
SetFactory("OpenCASCADE");
DefineConstant[ h = 0.005 ];
Cylinder(1) = {0, 0, 0, 0, 0, 0.15, 0.025};
Mesh.MeshSizeMax = h; Mesh.MeshSizeMin = h / 2;
Physical Surface("walls") = {1};
Physical Surface("outlet") = {2};
Physical Surface("inlet") = {3};
Physical Volume("fluid") = {1};
