"""The version of mkf_ros, defined once: ``mkf_ros.__version__`` and setup.py read it from here.

package.xml must carry the same number as a literal (ROS tools parse it without running Python);
test/test_packaging.py checks that they agree.
"""

__version__ = "0.1.0"
