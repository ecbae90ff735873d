"""Contact layer (paper §3): detection, the constraint Jacobian in JDS, compliance (warped or
exact), the frictional contact solver, and the stage that ties them after the free motion.

    obstacles.py           rigid obstacles: plane, sphere, capsule, box, triangle mesh; prescribed motion
    contacts.py            Contacts, the record of a step's contacts; the contact points a surface carries
    detection.py           proximity of surface points to obstacles and to other soft bodies
    geometry.py            ... the kernels' geometry: closest points, bounds tests, grid cells
    hits.py                ... what the kernels found: every body's hits in one buffer, read as Contacts
    constraints.py         H (normal, two tangents per contact; attachments) and its JDS storage
    compliance.py          W = Σ h (H R) A₀⁻¹ (H R)ᵀ by warping, or h H A⁻¹ Hᵀ exactly; the correction
    frictional_contact.py  the frictional contact problem (Coulomb friction): the solvers' entry point and dispatch
    cone.py                ... one contact's pieces: cone projection, natural-map error, exact 3×3 local solve
    layouts.py             ... W on the device (dense, block-CSR, factored) and the kernels' argpacks
    gauss_seidel.py        ... projected block Gauss-Seidel with Anderson acceleration (one launch)
    jacobi.py              ... relaxed block Jacobi (parallel)
    newton.py              ... semi-smooth Newton on the Alart–Curnier function (many coupled contacts)
    pipeline.py            ContactStage and its settings (Contact): detection → H → W → LCP → correction, timed
    layer.py               Obstacle scene options, the Contact group in a scene, the Simulation stage
"""

from .constraints import Attachment
from .contacts import Contacts
from .detection import Detector
from .delassus import FactoredDelassus
from .frictional_contact import ContactInfo, FrictionalContactSolver, natural_map_residual, solve_frictional_contact
from .layer import ContactLayer, Obstacle
from .obstacles import Box, Capsule, Plane, RigidObstacle, Sphere, TriangleMesh
from .pipeline import Contact, ContactBody, ContactResult, ContactStage

__all__ = ["Attachment", "Box", "Capsule", "Contact", "ContactBody", "ContactInfo", "ContactLayer", "ContactResult",
           "ContactStage", "Contacts", "Detector", "FactoredDelassus", "FrictionalContactSolver", "Obstacle", "Plane",
           "RigidObstacle", "Sphere", "TriangleMesh", "natural_map_residual", "solve_frictional_contact"]
