MODULE writer_test_S1
  ! project: writer test
  ! station: S1
  ! generator: fabflow test
  PERS tooldata t_gripper := [TRUE,[[0.000,0.000,250.000],[1.000000000,0.000000000,0.000000000,0.000000000]],[8.500,[0.000,10.000,120.000],[1,0,0,0],0,0,0]];
  PERS wobjdata wobj_world := [FALSE,TRUE,"",[[-2089.842,-795.337,-600.000],[0.998750260,0.000000000,0.000000000,-0.049979169]],[[0,0,0],[1,0,0,0]]];
  CONST jointtarget jhome := [[0.0000,0.0000,0.0000,0.0000,30.0000,0.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p1 := [[1104.496,910.150,830.000],[0.000000000,0.998750260,0.049979169,0.000000000],[-2,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p2 := [[1104.496,910.150,700.000],[0.000000000,0.998750260,0.049979169,0.000000000],[-2,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p3 := [[1104.496,910.150,830.000],[0.000000000,0.998750260,0.049979169,0.000000000],[-2,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p4 := [[3200.000,1000.000,830.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-2,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p5 := [[3200.000,1000.000,235.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-2,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p6 := [[3200.000,1000.000,105.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-2,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p7 := [[3200.000,1000.000,235.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-2,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p8 := [[1104.496,910.150,830.000],[0.000000000,0.998750260,0.049979169,0.000000000],[2,0,-4,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p9 := [[1104.496,910.150,700.000],[0.000000000,0.998750260,0.049979169,0.000000000],[2,0,-4,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p10 := [[1104.496,910.150,830.000],[0.000000000,0.998750260,0.049979169,0.000000000],[2,0,-4,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p11 := [[3000.000,1800.000,830.000],[0.000000000,0.707106781,0.707106781,0.000000000],[0,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p12 := [[3000.000,1800.000,340.000],[0.000000000,0.707106781,0.707106781,0.000000000],[0,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p13 := [[3000.000,1800.000,210.000],[0.000000000,0.707106781,0.707106781,0.000000000],[0,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p14 := [[3000.000,1800.000,340.000],[0.000000000,0.707106781,0.707106781,0.000000000],[0,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p15 := [[3400.000,600.000,400.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p16 := [[3400.000,600.000,300.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p17 := [[3500.000,650.000,300.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p18 := [[3600.000,600.000,300.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p19 := [[3600.000,600.000,400.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p20 := [[3000.000,500.000,400.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p21 := [[3000.000,500.000,300.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST robtarget p22 := [[3000.000,500.000,400.000],[0.000000000,1.000000000,0.000000000,0.000000000],[-1,0,-3,0],[9E9,9E9,9E9,9E9,9E9,9E9]];
  PERS loaddata load_B1 := [2.980,[0.000,0.000,52.500],[1,0,0,0],0,0,0];
  PROC main()
    VAR num answer;
    ConfJ \On;
    ConfL \On;
    TPWrite "fabflow: set the lift to 350 mm above its lowest position";
    TPReadFK answer, "Lift at 350 mm?", "OK", stEmpty, stEmpty, stEmpty, stEmpty;
    MoveAbsJ jhome\NoEOffs, v1000, fine, t_gripper\WObj:=wobj_world; ! home
    ! element B1
    MoveJ p1, v1000, z10, t_gripper\WObj:=wobj_world; ! B1 pick approach
    MoveL p2, v200, fine, t_gripper\WObj:=wobj_world; ! B1 pick
    SetDO do_gripper, 1;
    WaitTime 0.300;
    GripLoad load_B1;
    MoveL p3, v200, z10, t_gripper\WObj:=wobj_world; ! B1 pick retract
    MoveJ p4, v1000, z10, t_gripper\WObj:=wobj_world; ! B1 travel
    MoveJ p5, v1000, z10, t_gripper\WObj:=wobj_world; ! B1 place approach
    MoveL p6, v200, fine, t_gripper\WObj:=wobj_world; ! B1 place
    SetDO do_gripper, 0;
    WaitTime 0.300;
    GripLoad load0;
    MoveL p7, v200, z10, t_gripper\WObj:=wobj_world; ! B1 place retract
    ! element B2
    MoveJ p8, v1000, z10, t_gripper\WObj:=wobj_world; ! B2 pick approach
    MoveL p9, v200, fine, t_gripper\WObj:=wobj_world; ! B2 pick
    SetDO do_gripper, 1;
    WaitTime 0.300;
    MoveL p10, v200, z10, t_gripper\WObj:=wobj_world; ! B2 pick retract
    MoveJ p11, v1000, z10, t_gripper\WObj:=wobj_world; ! B2 travel
    MoveJ p12, v1000, z10, t_gripper\WObj:=wobj_world; ! B2 place approach
    MoveL p13, v200, fine, t_gripper\WObj:=wobj_world; ! B2 place
    SetDO do_gripper, 0;
    WaitTime 0.300;
    MoveL p14, v200, z10, t_gripper\WObj:=wobj_world; ! B2 place retract
    ! element P1
    MoveJ p15, v1000, z10, t_gripper\WObj:=wobj_world; ! P1 approach
    MoveL p16, v200, fine, t_gripper\WObj:=wobj_world; ! P1 start
    SetDO do_extruder, 1;
    MoveL p17, v100, z10, t_gripper\WObj:=wobj_world; ! P1 path 1
    MoveL p18, v100, fine, t_gripper\WObj:=wobj_world; ! P1 end
    SetDO do_extruder, 0;
    MoveL p19, v200, z10, t_gripper\WObj:=wobj_world; ! P1 retract
    ! element T1
    MoveJ p20, v1000, z10, t_gripper\WObj:=wobj_world; ! T1 approach
    MoveL p21, v200, fine, t_gripper\WObj:=wobj_world; ! T1 drill
    SetDO do_drill, 1;
    WaitTime 1.000;
    SetDO do_drill, 0;
    MoveL p22, v200, z10, t_gripper\WObj:=wobj_world; ! T1 retract
    MoveAbsJ jhome\NoEOffs, v1000, fine, t_gripper\WObj:=wobj_world; ! home
  ENDPROC
ENDMODULE
