"""Manipulation of found objects: the object database, grasp planning for a two-jaw
gripper and the choice of object for a slot (paper 002, sections 4.5 and 5).

Plain geometry on point clouds and meshes: no project, no sensors, no build.
"""
