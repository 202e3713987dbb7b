"""Object catalogue for synthetic scenes: names, categories and hand-written implicit queries.

Implicit descriptions never name the object (the paper's "a sturdy vessel designed for holding
hot beverages" for a coffee mug); the grounding benchmarks use them for implicit queries.
Categories group interchangeable objects; a scene holds at most one object per category where it
can, so that an implicit query has a single right answer.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CatalogueEntry:
    folder: str          # folder under objects/ or a pybullet_data URDF path
    name: str            # the explicit query
    category: str
    implicit: tuple[str, ...]
    scale: float = 1.0   # pybullet globalScaling


_CUP = (
    "something to drink water or juice from",
    "a small open container you would fill with a cold drink",
    "a drinking vessel without a handle",
)

# Objects from the shared textured-mesh folder (../shared/data/objects).
SHARED_OBJECTS: tuple[CatalogueEntry, ...] = (
    CatalogueEntry("plastic_apple", "apple", "apple", (
        "a round red fruit that keeps the doctor away",
        "a crunchy fruit you could bite into as a snack",
        "the fruit that fell on Newton's head")),
    CatalogueEntry("plastic_banana", "banana", "banana", (
        "a long curved yellow fruit that monkeys love",
        "a fruit you peel before eating, rich in potassium",
        "something sweet to eat that is shaped like a crescent")),
    CatalogueEntry("plastic_lemon", "lemon", "lemon", (
        "a very sour yellow citrus fruit",
        "something to squeeze over fish or into tea for a sour taste",
        "the citrus fruit used to make lemonade")),
    CatalogueEntry("plastic_orange", "orange", "orange", (
        "a round citrus fruit you peel and split into segments",
        "the fruit that is pressed to make a common breakfast juice",
        "a sweet citrus fruit full of vitamin C")),
    CatalogueEntry("plastic_peach", "peach", "peach", (
        "a soft fuzzy fruit with a large stone inside",
        "a juicy summer fruit with velvety skin",
        "a soft orange-pink fruit that is canned in syrup")),
    CatalogueEntry("plastic_pear", "pear", "pear", (
        "a fruit that is narrow at the top and wide at the bottom",
        "a sweet fruit shaped like a teardrop",
        "a green fruit with a grainy texture that ripens after picking")),
    CatalogueEntry("plastic_plum", "plum", "plum", (
        "a small purple stone fruit that dries into a prune",
        "a small dark fruit with a single pit",
        "a purple fruit that is made into jam")),
    CatalogueEntry("blue_cup", "blue cup", "cup", _CUP),
    CatalogueEntry("green_cup", "green cup", "cup", _CUP),
    CatalogueEntry("yellow_cup", "yellow cup", "cup", _CUP),
    CatalogueEntry("orange_cup", "orange cup", "cup", _CUP),
    CatalogueEntry("mug", "coffee mug", "mug", (
        "a sturdy vessel designed for holding hot beverages",
        "something with a handle to drink hot tea from",
        "a ceramic container for a warm drink in the morning")),
    CatalogueEntry("bowl", "bowl", "bowl", (
        "a round deep dish for soup or cereal",
        "a container to eat breakfast cereal with milk from",
        "a hollow dish for serving salad or noodles")),
    CatalogueEntry("doraemon_bowl", "cartoon bowl", "bowl", (
        "a round deep dish for soup or cereal",
        "a container to eat breakfast cereal with milk from",
        "a hollow dish for serving salad or noodles")),
    CatalogueEntry("spoon", "spoon", "spoon", (
        "a utensil for eating soup",
        "something to stir sugar into a cup of tea",
        "the cutlery for eating yogurt")),
    CatalogueEntry("fork", "fork", "fork", (
        "a pronged utensil for picking up food",
        "the cutlery you hold in the left hand to eat spaghetti",
        "something with tines to spear a piece of salad")),
    CatalogueEntry("knife", "knife", "knife", (
        "a utensil with a blade for cutting food",
        "something to spread butter on bread with",
        "the cutlery for slicing a steak")),
    CatalogueEntry("scissors", "scissors", "scissors", (
        "a tool with two blades for cutting paper",
        "something to cut a piece of ribbon or tape",
        "a cutting tool with two finger loops")),
    CatalogueEntry("stapler_1", "stapler", "stapler", (
        "an office tool that fastens sheets of paper together",
        "something that binds a stack of pages with a metal clip",
        "a desk gadget you press down to pin a report together")),
    CatalogueEntry("large_marker", "marker", "marker", (
        "a thick pen for writing on a whiteboard",
        "something to draw bold lines with ink",
        "a felt-tip pen for labelling boxes")),
    CatalogueEntry("mini_claw_hammer_1", "hammer", "hammer", (
        "a tool for driving nails into wood",
        "something heavy to pound with that can also pull out nails",
        "a carpenter's striking tool")),
    CatalogueEntry("flat_screwdriver", "flat screwdriver", "screwdriver", (
        "a tool for turning screws with a slotted head",
        "something to tighten a loose screw",
        "a hand tool with a straight blade-like tip")),
    CatalogueEntry("phillips_screwdriver", "phillips screwdriver", "screwdriver", (
        "a tool for turning screws with a cross-shaped head",
        "something to tighten a loose screw",
        "a hand tool with a cross-shaped tip")),
    CatalogueEntry("large_clamp", "clamp", "clamp", (
        "a tool that holds two pieces together tightly while glue dries",
        "something to press a workpiece firmly against a bench",
        "a gripping tool you tighten with a screw or lever")),
    CatalogueEntry("glue_1", "glue stick", "glue", (
        "something sticky for attaching paper to paper",
        "an adhesive used in arts and crafts",
        "a tube you twist up to paste a photo into a scrapbook")),
    CatalogueEntry("correction_fluid", "correction fluid", "correction fluid", (
        "a white liquid for covering up writing mistakes",
        "something to paint over a typo on paper",
        "an office bottle of white-out")),
    CatalogueEntry("remote_controller_1", "remote control", "remote control", (
        "a handheld device for changing television channels",
        "something to turn the TV volume up from the sofa",
        "a small gadget with buttons that works a device from a distance")),
    CatalogueEntry("remote_controller_2", "remote control", "remote control", (
        "a handheld device for changing television channels",
        "something to turn the TV volume up from the sofa",
        "a small gadget with buttons that works a device from a distance")),
    CatalogueEntry("shampoo", "shampoo", "shampoo", (
        "a liquid for washing your hair",
        "the bottle you use in the shower to clean your scalp",
        "a foaming hair cleanser")),
    CatalogueEntry("conditioner", "conditioner", "conditioner", (
        "a liquid that makes hair soft after washing",
        "the bottle used after washing to untangle hair",
        "a hair care product that adds smoothness")),
    CatalogueEntry("soap", "soap", "soap", (
        "a bar for washing your hands",
        "something that lathers when you rub it with water",
        "a cleansing block kept by the sink")),
    CatalogueEntry("toothpaste_1", "toothpaste", "toothpaste", (
        "something to squeeze onto a toothbrush",
        "a minty paste for cleaning teeth",
        "a tube you use every morning and night at the bathroom sink")),
)

# Fallback objects that ship with pybullet_data (used when the shared folder is missing).
PYBULLET_OBJECTS: tuple[CatalogueEntry, ...] = (
    CatalogueEntry("duck_vhacd.urdf", "rubber duck", "duck", (
        "a yellow bath toy that floats",
        "a toy bird children play with in the bathtub",
        "a squeaky toy that quacks")),
    CatalogueEntry("teddy_vhacd.urdf", "teddy bear", "teddy bear", (
        "a soft stuffed toy animal to cuddle",
        "a plush toy a child takes to bed",
        "a cuddly toy named after a president")),
    CatalogueEntry("objects/mug.urdf", "coffee mug", "mug", (
        "a sturdy vessel designed for holding hot beverages",
        "something with a handle to drink hot tea from",
        "a ceramic container for a warm drink in the morning")),
    CatalogueEntry("lego/lego.urdf", "lego brick", "lego brick", (
        "a small plastic building block with studs on top",
        "a toy piece that snaps onto others to build models",
        "a construction toy piece from Denmark"), scale=1.5),
    CatalogueEntry("jenga/jenga.urdf", "wooden block", "wooden block", (
        "a rectangular piece from a stacking tower game",
        "a small plank you pull out of a tower carefully",
        "a smooth timber brick"), scale=0.8),
    CatalogueEntry("cube_small.urdf", "cube", "cube", (
        "a small box shape with six equal square faces",
        "a block with all edges the same length",
        "a shape like a die without the dots")),
    CatalogueEntry("sphere_small.urdf", "ball", "ball", (
        "a small round object that rolls",
        "something perfectly round to throw and catch",
        "a sphere to play fetch with"), scale=1.5),
    CatalogueEntry("toys/concave_box.urdf", "toy box", "toy box", (
        "an open container for keeping small toys",
        "a small open crate without a lid",
        "somewhere to tidy away playthings"), scale=0.06),  # the mesh is 2 m x 2 m x 0.2 m
)
