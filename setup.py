from pathlib import Path

from setuptools import find_packages, setup

here = Path(__file__).parent
requirements = [
    line.strip()
    for line in (here / "requirements.txt").read_text().splitlines()
    if line.strip() and not line.startswith("#")
]

setup(
    name="findview",
    version="0.1.0",
    description="FindView: precise target view localization for look-around agents (simulator, task, baselines)",
    long_description=(here / "README.md").read_text() if (here / "README.md").exists() else "",
    long_description_content_type="text/markdown",
    python_requires=">=3.11",
    packages=find_packages(include=["findview", "findview.*", "findview_baselines", "findview_baselines.*"]),
    # the frost textures of the `frost` corruption (Apache-2.0, see the LICENSE and NOTICE next to them)
    package_data={"findview.corruptions": ["frost/*.png", "frost/*.jpg", "frost/LICENSE-imagecorruptions", "frost/NOTICE"]},
    install_requires=requirements,
    extras_require={
        "dev": ["pytest==9.2.0", "gymnasium==1.4.0"],
        "gym": ["gymnasium>=1.0"],
        # the reference renderer used only by benchmarks/ (the authors' renderer)
        "bench": ["pyequilib==0.5.8"],
    },
)
